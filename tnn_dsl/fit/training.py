"""Training a network: :func:`train` (one trainer for both backends, thesis §4.5, eq. 4.6–4.8; see
:mod:`.trainer` for how it works) and :func:`evaluate`."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import os
import time
from typing import Any, Callable, Mapping

import numpy as np

from ..core import Diagnostic, TnnError
from ..core.interrupt import is_interrupt
from ..data import as_experiments
from ..ir import Network
from .config import TrainConfig, load_config, one_sequence_per_file, single_shooting_route, torch_compile_pays
from .estimates import check_objective, estimation_meta, ml_refit, output_error_summary
from .model_files import MODEL_DIR, TrainedModel, data_records, load_model, versions
from .trainer import _net_of, _Trainer

__all__ = ["TrainConfig", "train", "evaluate", "load_config"]

# ---------------------------------------------------------------------------------------------
# Public API
# ---------------------------------------------------------------------------------------------


def train(network: Network | str | os.PathLike, data: Any, val: Any = None, *,
          config: TrainConfig | dict | str | os.PathLike | None = None,
          out: str | os.PathLike | None = None, force: bool = False,
          callback: Callable[[dict], None] | None = None,
          log: Callable[[str], None] | None = None, start: Mapping[str, Any] | None = None,
          **options: Any) -> TrainedModel:
    """Fit a network's free parameters and learned functions to data (thesis eq. 4.8).

    Parameters
    ----------
    network : Network or path to a ``.thn`` file
    data : training data: path(s) or ``Experiment``(s); several files are trained together
    val : validation data (path(s) or ``Experiment``s); validation is a free run over each experiment.
        Without it, ``val_fraction`` holds out the end of each training file, else the training loss
        decides early stopping.
    config : :class:`TrainConfig`, a dict of options or a YAML file; ``**options`` override it.
    out : model directory to write (atomically), also after Ctrl-C or divergence (best state kept). It is
        checked before training starts: it must be absent, empty or a model directory, unless ``force``
        (then the model's files are written into the directory and its other files are kept).
    callback : ``f(info)`` after each epoch: ``epoch, epochs, phase, loss, val_mae, best_val_mae,
        elapsed, eta`` (s).
    log : ``f(message)`` for notes and warnings (default: silent).
    start : starting values, ``{parameter name: array}`` in the compiled model's names and shapes (SI): a physical
        parameter (``pe.seebeck``) or a learned function's arrays (``fn.W``, ``fn.x_mean``; a function given any
        array keeps the given statistics, as with ``init_from``); names this network does not have, or of another
        shape, are ignored. They win over ``init_from``. The model doctor's MLP check starts from its own fit with
        it (:mod:`tnn_dsl.doctor.mlp_check`).

    Returns a :class:`TrainedModel`; ``meta["metrics"]`` holds training and validation errors (K),
    ``meta["curve"]`` the training curve, ``meta["stopped"]`` why training ended
    (``completed``, ``early_stopping``, ``time_limit``, ``interrupted``, ``diverged``)."""
    from ..compiler import compile as compile_network
    from ..core import check_output
    from ..data import split_by_time

    cfg = make_config(config, options)
    if out is not None:
        check_output(out, MODEL_DIR, force=force, inputs=[*_input_paths(network, data, val), cfg.init_from])
    net = _net_of(network)
    exps = as_experiments(net, data)
    if not exps:
        raise TnnError(Diagnostic("no training data given", hint="pass at least one CSV or Parquet file"))
    vals = as_experiments(net, val)
    if not vals and cfg.val_fraction > 0:
        parts = [split_by_time(e, 1.0 - cfg.val_fraction) for e in exps]
        exps, vals = [a for a, _ in parts], [b for _, b in parts]
    for e in exps + vals:
        if e.n_steps < 2:
            raise TnnError(Diagnostic(f"{e.path}: {e.name} has {e.n_steps} sample(s); training needs at least 2",
                                      hint="pass a longer data file"))
        if not np.isfinite(np.asarray(e.outputs, dtype=float)).any():
            raise TnnError(Diagnostic(f"{e.path}: {e.name} has no sensor measurement at all",
                                      hint="check the sensor columns named in the network"))
    check_objective(net, cfg.objective, cfg.backend)
    one_sequence, single_route = one_sequence_per_file(cfg, exps), single_shooting_route(cfg, exps)
    auto = torch_compile_pays(cfg, sum(e.n_steps for e in exps + vals), one_sequence, single_route)
    if auto is not None and auto != cfg.torch_compile:
        cfg = dataclasses.replace(cfg, torch_compile=auto)
        if auto and log is not None:
            how = (", each file one sequence" if one_sequence
                   else ", windows, then each file one sequence" if single_route else "")
            log(f"torch: compiling the rollouts ({sum(e.n_steps for e in exps + vals)} samples × {cfg.epochs} "
                f"epochs{how}; torch_compile=False or TNN_TORCH_COMPILE=0 to run eager)")
    model = compile_network(net, backend=cfg.backend, dtype=cfg.dtype, torch_compile=cfg.torch_compile)
    t_start = time.perf_counter()
    with _compile_beside(net, exps, vals, cfg, model, log) as beside:
        tr, z, strategy, compile_s = _best_route(net, exps, vals, cfg, model, callback, log, start)
    if log is not None and getattr(beside, "outcome", None):
        log(f"torch: {beside.outcome}")
    final = tr.numpy_params(z)
    initial_states = tr.fitted_initial_states(z)
    per_experiment = tr.experiment_values(z)
    # the metrics below are free runs with the training's integrator and sub-steps (meta["config"])
    trained = TrainedModel(net, final, meta={"initial_states": initial_states, "per_experiment": per_experiment,
                                             "config": cfg.to_dict()}, path=None)
    trained._models[(cfg.backend, cfg.dtype)] = model
    est = _estimates(trained, model, exps, cfg, tr)
    trained.meta = model_meta(trained, tr, model, exps, vals, cfg, est, fitted=_fitted(tr, model, final),
                              strategy=strategy, seconds=time.perf_counter() - t_start, compile_seconds=compile_s)
    if out is not None:
        trained.save(out, force=force)
    return trained


def make_config(config: TrainConfig | dict | str | os.PathLike | None, options: dict[str, Any]) -> TrainConfig:
    """The :class:`TrainConfig` of ``train(config=..., **options)``: options override the config."""
    if isinstance(config, TrainConfig):
        return dataclasses.replace(config, **{k: v for k, v in options.items() if v is not None})
    if isinstance(config, dict):
        return load_config(None, **{**config, **options})
    return load_config(config, **options)


_CUT_SHORT = ("interrupted", "diverged", "time_limit")


def model_meta(trained: TrainedModel, tr: _Trainer, model: Any, exps: list, vals: list, cfg: TrainConfig, est: Any,
               *, fitted: dict[str, Any], strategy: Any, seconds: float,
               compile_seconds: float | None = None) -> dict[str, Any]:
    """``meta.json`` of a fitted model: ``trained`` (its parameters, ``meta["initial_states"]`` and
    ``meta["per_experiment"]`` set) after the trainer ``tr`` on ``exps`` (validation ``vals``), with the estimates
    ``est`` (or ``None``); its training and validation errors are computed here (free runs). ``seconds``: the
    whole training (s); ``compile_seconds``: the part of it in the first calls of its compiled programs (s,
    default ``tr``'s; ``time_limit`` does not count them)."""
    metrics: dict[str, Any] = {}
    for key, sets in (("train", exps), ("validation", vals)):
        if sets:
            metrics[key] = _metrics_or_nan(trained, sets, cfg, tr)
            if metrics[key].get("interrupted"):  # Ctrl-C: the next data set's errors are not computed either
                if vals:
                    metrics["validation"] = {"mae": math.nan, "interrupted": True}
                break
    net = trained.network
    return {
        "network": net.name,
        "backend": cfg.backend,
        "dtype": cfg.dtype,
        "versions": versions(cfg.backend),
        "data": {"train": _data_desc(exps), "validation": _data_desc(vals)},
        "data_files": data_records(sorted({e.path for e in exps + vals if getattr(e, "path", None)})),
        "normalisation": tr.normalisation,
        "metrics": metrics,
        "fitted": fitted,
        "curve": tr.curve,
        "config": cfg.to_dict(),
        **_rollout_meta(tr),
        "strategies": strategy,
        "init": cfg.init,
        "initial_states": trained.meta.get("initial_states") or [],
        "per_experiment": trained.meta.get("per_experiment") or [],
        "objective": cfg.objective,
        "estimation": estimation_meta(est) if est is not None else None,
        "stopped": tr.stopped,
        "warnings": list(tr.warnings),
        "train_seconds": seconds,
        "compile_seconds": tr.warmup_s if compile_seconds is None else compile_seconds,
    }


def _estimates(trained: TrainedModel, model: Any, exps: list, cfg: TrainConfig, tr: _Trainer) -> Any:
    """The likelihood fit (``objective="ml"``, which updates ``trained``) or the output-error fit's standard
    errors; ``None`` (with a warning) where they cannot be had — a fit that was cut short, a model that does
    not run — the trained model is kept either way."""
    if tr.stopped in ("interrupted", "diverged"):
        return None
    try:
        if cfg.objective == "ml":
            return ml_refit(trained, model, exps, cfg, tr.log)
        return output_error_summary(trained, model, exps, cfg)
    except (KeyboardInterrupt, SystemError) as e:
        if not is_interrupt(e):
            raise
        tr.note_interrupt("while estimating " + ("by maximum likelihood; kept the output-error fit"
                                                 if cfg.objective == "ml" else "standard errors; none given"))
        return None
    except (TnnError, FloatingPointError, np.linalg.LinAlgError, ValueError) as e:
        msg = e.diagnostics[0].message if isinstance(e, TnnError) and getattr(e, "diagnostics", None) else str(e)
        what = "the likelihood fit" if cfg.objective == "ml" else "standard errors"
        tr.warnings.append(f"no {what}: {msg}")
        tr.log(f"warning: no {what}: {msg}")
        return None


def _best_route(net: Network, exps: list, vals: list, cfg: TrainConfig, model: Any, callback: Any, log: Any,
                start: Mapping[str, Any] | None = None):
    """The fit → ``(trainer, z, strategies or None)``. Where the trainer goes on as single shooting after its
    windows (:meth:`~.rollouts._Rollouts.wants_single_shooting_finish`), there are two routes to the free run the
    model is judged by: the windowed fit polished as single shooting, and single shooting from the start; the
    better one (validation MAE, else the free-run training loss) is kept and both scores are returned. Both routes
    begin at ``start`` (:func:`train`)."""
    tr, z = _fit(net, exps, vals, cfg, model, callback, log, start)
    if not (tr.wants_single_shooting_finish() and tr.stopped not in _CUT_SHORT):
        return tr, z, None, tr.warmup_s
    # Ctrl-C from here on keeps the best result so far. The windowed trainer is finished as a shallow copy: the
    # switch of layout rebinds the copy's attributes, so the windowed one and its ``z`` stay valid together.
    finishing = copy.copy(tr)
    try:
        z_f = finishing.finish_single_shooting(z)
    except (KeyboardInterrupt, SystemError) as e:
        if not is_interrupt(e):
            raise
        tr.note_interrupt("while switching to single shooting; kept the multiple-shooting fit")
        return tr, z, None, tr.warmup_s
    tr, z = finishing, z_f
    if tr.stopped == "interrupted":  # the single-shooting polish was stopped: not a second route
        return tr, z, None, tr.warmup_s
    try:
        tr_s, z_s = _fit(net, exps, vals, dataclasses.replace(cfg, rollout="free"), model, callback, log, start)
        a, b = tr.selection_score(z), tr_s.selection_score(z_s)
    except (KeyboardInterrupt, SystemError) as e:
        if not is_interrupt(e):
            raise
        tr.note_interrupt("during the single-shooting route; kept the multiple-shooting fit polished as single "
                          "shooting")
        return tr, z, None, tr.warmup_s
    if tr_s.stopped == "interrupted":  # the first route is kept below (a route cut short does not win) and says so
        tr.note_interrupt("during the single-shooting route; kept the multiple-shooting fit polished as single "
                          "shooting")
    compile_s = tr.warmup_s + tr_s.warmup_s  # both routes trained
    by = "validation MAE" if vals else "free-run training loss"
    if tr_s.stopped not in _CUT_SHORT and b < a:
        tr, z = tr_s, z_s
    elif tr_s.stopped == "time_limit" and tr.stopped not in _CUT_SHORT:
        # the route kept finished, but the choice between the two did not: with more time the other might have won,
        # so the training as a whole was cut by the limit and says so (it said "completed": the doctor's MLP check
        # took such a training as decided)
        tr.stopped = "time_limit"
        tr.log("the time limit stopped the single-shooting route before it ended: the other route is kept, and the "
               "training reported as cut by the time limit")
    tr.log(f"kept {'single shooting' if tr is tr_s else 'multiple shooting, then single shooting'} "
           f"({by} {min(a, b):.4g} against {max(a, b):.4g})")
    return tr, z, {"windows_then_single": a, "single": b, "by": by, "single_stopped": tr_s.stopped}, compile_s


def _rollout_meta(tr: _Trainer) -> dict[str, Any]:
    """``rollout``, ``window_s`` and ``single_shooting`` of a finished trainer, for ``meta.json``."""
    if tr.windowed:  # multiple shooting, then single shooting
        rollout, window_s = tr.windowed
    elif tr.single_shooting:
        rollout, window_s = "free", None
    else:
        rollout, window_s = tr.mode, (None if tr.mode == "free" else tr.window)
    return {"rollout": rollout, "window_s": window_s, "single_shooting": bool(tr.single_shooting)}


def _fitted(tr: _Trainer, model: Any, final: dict[str, np.ndarray]) -> dict[str, dict[str, Any]]:
    """Each free physical parameter's fitted and initial value (SI), for ``meta.json``."""
    return {sl.name: {"value": final[sl.name].tolist(), "initial": tr.params0[sl.name].tolist()}
            for sl in tr.slots if "@" not in sl.name and model.param_specs[sl.name].kind == "physical"}


def _compile_beside(net: Network, exps: list, vals: list, cfg: TrainConfig, model: Any, log: Any):
    """A helper process compiling the training's reverse scan while the training compiles its forward one
    (:class:`~.compile_ahead.CompileBeside`), where :func:`~.compile_ahead.beside_wanted` says it pays for this
    model (compiled on torch); else nothing."""
    from .compile_ahead import CompileBeside, beside_wanted

    if not beside_wanted(cfg.backend, getattr(model, "torch_compile", False)):
        return contextlib.nullcontext()
    if log is not None:
        log("torch: a helper process compiles the gradient's reverse scan beside this training "
            "(TNN_COMPILE_AHEAD=0 turns it off)")
    return CompileBeside(net, exps, vals, cfg.to_dict())


def _fit(net: Network, exps: list, vals: list, cfg: TrainConfig, model: Any, callback: Any, log: Any,
         start: Mapping[str, Any] | None = None):
    """One training run (nominal run, normalisation, layout, rollouts, Adam, L-BFGS) → ``(trainer, z)``."""
    tr = _Trainer(net, exps, vals, cfg, model, callback=callback, log=log, start=start)
    params = tr.initial_params()
    nom, nom_bp, runs = tr.nominal_runs(params)
    tr.set_stats(params, nom, nom_bp, runs)
    tr.prefit_replace(params, nom, nom_bp, runs)
    tr.layout(params)
    tr.build_batches(runs)
    return tr, tr.run()


def _input_paths(network, data, val) -> list:
    """The files a training run reads (for the output check): the network's sources and the data paths."""
    paths: list = []
    if isinstance(network, (str, os.PathLike)):
        paths.append(network)
    else:
        paths.extend(getattr(network, "source_files", ()) or ())
    for d in (data, val):
        items = d if isinstance(d, (list, tuple)) else [d]
        paths.extend(x if isinstance(x, (str, os.PathLike)) else getattr(x, "path", None) for x in items)
    return paths


def _metrics_or_nan(trained, exps, cfg, tr: _Trainer):
    """The free-run errors of ``trained`` on ``exps``; NaN where the model leaves the physical range, or where
    Ctrl-C stops the run (the model is saved either way)."""
    try:
        return trained.evaluate(exps, backend=cfg.backend, init=cfg.init, burn_in_s=cfg.burn_in)
    except (FloatingPointError, TnnError):  # a model that leaves the physical range is still saved
        return {"mae": math.nan}
    except (KeyboardInterrupt, SystemError) as e:
        if not is_interrupt(e):
            raise
        tr.note_interrupt("while computing the model's errors; saved without them")
        return {"mae": math.nan, "interrupted": True}


def _data_desc(exps) -> list[dict[str, Any]]:
    return [{"name": e.name, "path": getattr(e, "path", None), "n_samples": int(e.n_steps), "dt": float(e.dt),
             "t0": float(np.asarray(e.t)[0]), "notes": list(getattr(e, "notes", ()))} for e in exps]


def evaluate(model: TrainedModel | str | os.PathLike, data: Any, backend: str | None = None,
             init: str = "estimate", burn_in_s: float | None = None) -> dict[str, Any]:
    """Errors of a trained model (a :class:`TrainedModel` or a model directory) on data: per-sensor and
    overall MAE, max error (thesis eq. 4.9), bias and RMSE in K, of a free run started by the initial-state
    rule ``init`` (:mod:`tnn_dsl.fit.initial`; the burn-in it is estimated on is not scored)."""

    tm = model if isinstance(model, TrainedModel) else load_model(model)
    return tm.evaluate(data, backend=backend, init=init, burn_in_s=burn_in_s)
