"""Estimates with their uncertainty after a fit, under either objective (``TrainConfig.objective``).

* ``output-error`` (default): the trainer's free-run fit; standard errors from the Gauss–Newton information
  (:func:`tnn_dsl.estimation.output_error_estimates`) at the fitted values, over the part of each training file
  that is scored, from the initial state the free run starts from.
* ``ml``: the continuous–discrete EKF likelihood (:func:`tnn_dsl.estimation.fit_ml`) maximised over the free
  constants and learned functions' weights, a process-noise level per state, a measurement-noise level per sensor
  and each training file's initial state — with standard errors from the Hessian of ``−log L``. Two starts: the
  output-error fit (its initial states too) and the values written in the network (the learned weights of the
  output-error fit); the higher likelihood is kept and the note says which start won and what the other reached.
  The output-error optimum is often a poor start for the likelihood (Bacher & Madsen's TiTh from it: log L 2684,
  from the written values 3904.7; TiTeTh 5296 against 5437.1), because the free-run fit lets a fast node absorb
  what the filter explains as process noise. The model keeps the likelihood's estimates.

Both give an :class:`~tnn_dsl.estimation.Estimates` (log-likelihood, AIC, BIC, the coefficient table), stored in
``meta.json`` under ``"estimation"`` (:func:`estimation_meta`).
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from ..core import Diagnostic, TnnError
from ..estimation import Estimates, fit_ml, output_error_estimates
from ..estimation.estimates import file_temperatures
from .config import OBJECTIVES
from .initial import free_run_start
from .simulation import free_run

__all__ = ["OBJECTIVES", "scored_records", "output_error_summary", "ml_refit", "estimation_meta",
           "check_objective"]


def check_objective(net: Any, objective: str, backend: str) -> None:
    """Refuse, before any work, what the chosen objective cannot do."""
    if objective == "ml":
        pe = [p.name for p in net.params if getattr(p, "per_experiment", False)]
        if pe:
            raise TnnError(Diagnostic(
                f"--objective ml does not estimate per-experiment parameters ({', '.join(pe)}) yet",
                hint="fit with --objective output-error, or make them ordinary free parameters"))
        if not net.sensors:
            raise TnnError(Diagnostic(f"network {net.name!r} has no sensors; the likelihood needs one",
                                      hint="declare `sensor NAME = NODE column \"...\"`"))


def scored_records(trained: Any, model: Any, exps: list, cfg: Any) -> list[tuple[str, np.ndarray, np.ndarray,
                                                                                   float, np.ndarray]]:
    """``(name, inputs, outputs, dt, T0)`` per training file: the part from where its free run starts (the
    initial-state rule of the fit; a training file's own fitted state), with that state."""
    params = trained.backend_params(cfg.backend)
    known = trained.free_run_context()
    out = []
    for e in exps:
        run = free_run(model, params, e, cfg.init, integrator=cfg.integrator, substeps=cfg.substeps,
                       burn_in_s=cfg.burn_in, **known)
        at = int(run.init.at)
        U = np.asarray(e.inputs, dtype=np.float64)[at:]
        Y = np.asarray(e.outputs, dtype=np.float64)[at:]
        out.append((str(e.name), U, Y, float(e.dt), np.asarray(run.init.T, dtype=np.float64)))
    return out


def _free_constants(model: Any, net: Any, cfg: Any = None) -> list[str]:
    """The constants the training fitted: free in the network, not per experiment, not held by ``cfg.freeze``."""
    pe = {p.name for p in net.params if getattr(p, "per_experiment", False)}
    held = set(getattr(cfg, "freeze", None) or ())
    return [k for k, s in model.param_specs.items()
            if s.kind == "physical" and s.trainable and k not in pe and k not in held]


def _held_note(model: Any, cfg: Any) -> list[str]:
    """The note for constants a training held at their values (``freeze``): the estimates are conditional on them,
    which have no standard errors (they were not estimated)."""
    held = set(getattr(cfg, "freeze", None) or ())
    names = [k for k, s in model.param_specs.items() if s.kind == "physical" and s.trainable and k in held]
    return [f"conditional on {', '.join(names)} (held at their values by this training's freeze: not estimated, "
            "no standard errors)"] if names else []


def output_error_summary(trained: Any, model: Any, exps: list, cfg: Any) -> Estimates:
    """Standard errors of the trainer's fit (module docstring). Constants the training held (``cfg.freeze``) are not
    among the estimates: they were not fitted."""
    notes = []
    if trained.network.learned:
        notes.append("conditional on the learned functions' weights (held at their fitted values)")
    if any(getattr(p, "per_experiment", False) for p in trained.network.params):
        notes.append("conditional on the per-experiment values (held at their fitted values)")
    notes += _held_note(model, cfg)
    est = output_error_estimates(model, trained.backend_params(cfg.backend), scored_records(trained, model, exps, cfg),
                                 free=_free_constants(model, trained.network, cfg), integrator=cfg.integrator,
                                 substeps=cfg.substeps, notes=notes)
    return file_temperatures(est, trained.network)


def ml_refit(trained: Any, model: Any, exps: list, cfg: Any, log: Callable[[str], None] | None = None) -> Estimates:
    """Maximise the EKF likelihood from the output-error fit and write the estimates into ``trained`` (its
    parameters and its training files' initial states). Returns the fit's :class:`Estimates`."""
    recs = scored_records(trained, model, exps, cfg)
    free = _free_constants(model, trained.network, cfg)  # never what the training held (freeze)
    held = set(getattr(cfg, "freeze", None) or ())
    free += [k for k, s in model.param_specs.items()
             if s.kind == "weights" and s.trainable and k not in held and k.split(".", 1)[0] not in held]
    records = [SimpleNamespace(name=n, inputs=U, outputs=Y, dt=dt) for n, U, Y, dt, _ in recs]
    fitted = trained.backend_params(cfg.backend)
    written = model.to_numpy(fitted)
    for p in trained.network.params:
        if p.name in free and p.value is not None:
            written[p.name] = np.asarray(float(p.value))
    starts = [("the output-error fit", fitted, [T0 for *_, T0 in recs]),
              ("the values written in the network", model.from_numpy(written), None)]
    results = []
    for label, params, x0 in starts:
        try:
            results.append((label, fit_ml(model, records, backend=cfg.backend, free=free, params=params, x0=x0,
                                          integrator=cfg.integrator, substeps=cfg.substeps)))
        except (TnnError, FloatingPointError, np.linalg.LinAlgError) as e:
            if log is not None:
                log(f"note: the likelihood fit from {label} failed: {str(e).splitlines()[0]}")
    good = [(lab, r) for lab, r in results if np.isfinite(r.loglik)]
    if not good:
        raise TnnError(Diagnostic("the likelihood fit failed from every start",
                                  hint="check the network's values and ranges, or use --objective output-error"))
    label, est = max(good, key=lambda lr: lr[1].loglik)
    others = ", ".join(f"{r.loglik:.2f} from {lab}" for lab, r in good if r is not est)
    est.notes.insert(0, f"started from {label} (log L {est.loglik:.2f}" + (f"; {others}" if others else "") + ")")
    est.notes += _held_note(model, cfg)
    if log is not None:
        log(f"likelihood fit: log L {est.loglik:.2f} from {label}" + (f" ({others})" if others else ""))
    new = {name: np.asarray(v, dtype=np.float64).reshape(np.shape(trained.params[name]))
           for name, v in est.fitted.items()}
    # each training file's stored start is refitted for a free run with the new parameters (free_run_start):
    # the likelihood's x0 (in the table) is the filter's prior mean, loose for an unsensed node
    names = list(model.state_names)
    base = model.to_numpy(trained.backend_params(cfg.backend))
    params = model.from_numpy({**base, **{k: v for k, v in new.items() if k in base}})
    by_name = {n: free_run_start(trained.network, model, params, U, Y, dt, integrator=cfg.integrator,
                                 substeps=cfg.substeps)[0] for n, U, Y, dt, _ in recs}
    # written into ``trained`` only now, all together: a Ctrl-C before this line leaves the output-error fit whole
    trained.params.update(new)
    for rec in trained.meta.get("initial_states") or []:
        T = by_name.get(rec.get("name"))
        if T is not None:
            rec["T0"] = {n: float(v) for n, v in zip(names, T)}
    file_temperatures(est, trained.network)
    if log is not None and not est.converged:
        log(f"warning: the likelihood fit did not converge ({est.message}); its estimates are kept, check them")
    return est


def estimation_meta(est: Estimates) -> dict[str, Any]:
    """``meta.json``'s ``"estimation"``: :meth:`Estimates.to_dict` with the covariance and correlation restricted
    to the rows shown (a learned function's weights are counted, not listed)."""
    d = est.to_dict()
    shown = [i for i, lab in enumerate(est.labels) if _is_row_label(lab)]
    for key, M in (("cov_z", est.cov_z), ("corr", est.corr)):
        sub = np.asarray(M, dtype=np.float64)[np.ix_(shown, shown)] if len(shown) else np.zeros((0, 0))
        d[key] = [[float(x) if np.isfinite(x) else None for x in row] for row in sub]
    d["labels"] = [est.labels[i] for i in shown]
    for key in ("z", "grad"):
        d[key] = [d[key][i] for i in shown] if d.get(key) is not None else None
    d.pop("fitted", None)  # the values are the model's parameters
    return d


def _is_row_label(label: str) -> bool:
    """A label of ``z`` shown as a row (not a learned function's weight ``NAME[i]``)."""
    base = label[4:] if label.startswith("log ") else label
    head = base.split("[")[0]
    return head in ("sigma_w", "sigma_v", "x0", "p0_std") or "[" not in base
