"""The doctor's likelihood objective (``--objective ml``): Bacher & Madsen's forward selection with the doctor's
candidates and its held-out guard.

Each round the output-error machinery still proposes (score test, shortlist, a proper output-error fit of each
shortlisted candidate). Under ``ml`` every candidate whose output-error fit did not diverge is then written as a
network (the current model plus that one element, :func:`~tnn_dsl.doctor.extension.extend_network`; new capacities
and resistances bounded to their plausible range, :func:`with_plausible_bounds`) and fitted by maximum
likelihood of the one-step predictor (the continuous–discrete Kalman filter; :func:`tnn_dsl.fit.train` with
``objective="ml"``, two starts, the better kept) on the training rows only, and judged physical or not on the
values it reaches (:mod:`.plausibility`). A physical candidate is accepted when

* the likelihood-ratio test against the current model passes: ``LR = 2(log L₁ − log L₀)`` against χ² on the
  added estimated quantities (parameters, noise levels, initial states), Bonferroni-corrected over the candidates
  fitted in the round, ``p <`` :data:`P_LR`;
* the held-out check passes: the one-step log-likelihood of the held-out rows (each held-out file's filter started
  from its estimated initial state, burn-in not scored) is higher, by a Diebold–Mariano test on the per-sample
  differences charged for the added quantities (:func:`tnn_dsl.analysis.held_out_loglik_test`), ``p <``
  :data:`P_LR`;

and of those the one with the largest training log-likelihood is taken (the likelihood's order). Without held-out
files the last 30 % of each training file is held out (and not fitted on)."""

from __future__ import annotations

import math
import time as _time
from dataclasses import replace
from typing import Any, Callable

import numpy as np
from scipy import stats

from ..analysis import held_out_loglik_test
from ..analysis.comparison import OBJECTIVES, ModelFit, fit_and_score
from ..core import TnnError
from ..ir import Network
from .engine import X0_PREFIX

__all__ = ["P_LR", "OBJECTIVES", "LikelihoodSelection", "with_ml_values", "likelihood_summary",
           "with_plausible_bounds"]

P_LR = 0.05  # the likelihood-ratio test and the held-out check, each


def _for(net: Network, exps: list) -> list:
    """``exps`` (read for the doctor's network, every data column an input) with only ``net``'s inputs."""
    out = []
    for e in exps:
        if tuple(e.input_names) == tuple(net.input_names):
            out.append(e)
            continue
        names = list(e.input_names)
        idx = [names.index(n) for n in net.input_names]
        cols = tuple(e.input_columns[i] for i in idx) if len(e.input_columns) == len(names) else e.input_columns
        out.append(replace(e, inputs=np.asarray(e.inputs)[:, idx], input_names=tuple(net.input_names),
                           input_columns=cols))
    return out


class LikelihoodSelection:
    """The likelihood side of one diagnosis: the data split, the current model's fit, each candidate's fit and
    test. ``train``/``val``: the doctor's experiments (``val`` empty: the last 30 % of each training file)."""

    def __init__(self, train: list, val: list, backend: str, burn_in_s: float | None,
                 say: Callable[[str], None]):
        if not val:
            from ..data import split_by_time

            parts = [split_by_time(e, 0.7) for e in train]
            train, val = [a for a, _ in parts], [b for _, b in parts]
        self.train, self.val, self.say = list(train), list(val), say
        self.options: dict[str, Any] = {"backend": backend}
        if burn_in_s is not None:
            self.options["burn_in"] = float(burn_in_s)
        self.current: ModelFit | None = None
        self.current_net: Network | None = None

    def fit(self, label: str, net: Network) -> ModelFit | None:
        """``net`` fitted by maximum likelihood on the training rows and scored on the held-out ones (``None``, with
        a line said, when no start gives a finite likelihood)."""
        t0 = _time.monotonic()
        try:
            f = fit_and_score(label, net, _for(net, self.train), _for(net, self.val), "ml", self.options, None,
                              val_in_training=False)
        except (TnnError, FloatingPointError, np.linalg.LinAlgError, ValueError) as exc:
            self.say(f"    likelihood fit of {label} failed: {str(exc).splitlines()[0]}")
            return None
        if f.loglik is None or not math.isfinite(f.loglik):
            self.say(f"    likelihood fit of {label}: no finite likelihood")
            return None
        self.say(f"    log L {f.loglik:.2f} (k = {f.k}) in {_time.monotonic() - t0:.1f} s"
                 + ("" if f.converged else ", NOT converged"))
        return f

    def start(self, net: Network) -> bool:
        """Fit the nominal model; ``False`` when it has no likelihood (the selection cannot run under ``ml``)."""
        self.say(f"fitting the nominal model by maximum likelihood ({len(self.train)} training part(s)) ...")
        self.current, self.current_net = self.fit("the nominal model", net), net
        return self.current is not None

    def test(self, cand: ModelFit, m: int) -> dict[str, Any]:
        """The likelihood-ratio test of ``cand`` against the current model (Bonferroni over ``m`` candidates) and
        the held-out check: the evidence a finding shows."""
        cur = self.current
        assert cur is not None
        lr = 2.0 * (float(cand.loglik) - float(cur.loglik))
        df = int(cand.k or 0) - int(cur.k or 0)
        p_lr = float(min(1.0, max(m, 1) * stats.chi2.sf(lr, df))) if lr > 0 and df > 0 else 1.0
        l0, l1 = cur.one_step_loglik_rows, cand.one_step_loglik_rows
        if l0 is not None and l1 is not None and len(l0) == len(l1):
            dm, p_val, n_eff = held_out_loglik_test(np.asarray(l0), np.asarray(l1), max(df, 0))
            ok = np.isfinite(l0) & np.isfinite(l1)
            gain = float(np.sum(l1[ok] - l0[ok]))
        else:
            dm, p_val, n_eff, gain = 0.0, 1.0, 0.0, math.nan
        return {"loglik_before": float(cur.loglik), "loglik": float(cand.loglik), "lr": lr, "df": df, "p_lr": p_lr,
                "m": m, "val_loglik_gain": gain, "dm_loglik": dm, "p_val_loglik": p_val, "n_eff_loglik": n_eff,
                "converged": cand.converged, "one_step_rms_before": cur.one_step_rms, "one_step_rms": cand.one_step_rms,
                "free_run_mae_ml": cand.free_run_mae,
                "estimates": _new_rows(cand, self.current_net)}

    def accept(self, cand: ModelFit, net: Network) -> None:
        self.current, self.current_net = cand, net


def with_plausible_bounds(net: Network, cand: Any, scales: Any) -> Network:
    """``net`` with the new capacity (and, behind a source, resistance) of a structural candidate ``cand`` bounded to
    the plausible range of its kind (:class:`~tnn_dsl.doctor.plausibility.Scales`), its value moved inside. Without
    the bounds the likelihood of a capacity behind a source slides, from a short time constant, to ``C → 0, R → ∞``
    at a fixed ``C·R`` (the one combination a single sensor sees; Bacher & Madsen's heater node ends there unless
    started near its optimum), a node thousands of kelvin hot."""
    el = cand.element
    ranges: dict[str, tuple[float, float]] = {}
    if cand.kind in ("thermal_mass", "source_mass") and scales.capacity is not None:
        ranges[el["param"]] = scales.capacity
    if cand.kind == "source_mass" and scales.resistance is not None:
        ranges[el["res"]] = scales.resistance
    if not ranges:
        return net
    from ..ir import Num

    params = []
    for p in net.params:
        if p.name in ranges and p.value is not None:
            lo, hi = ranges[p.name]
            upd: dict[str, Any] = {"lower": lo, "upper": hi}
            if not lo <= p.value <= hi:  # SI, kept in SI (the printer writes it in the file's units)
                upd.update(expr=Num(value=float(np.clip(p.value, lo, hi)), dim=dict(p.dim)), unit=None)
            params.append(p.model_copy(update=upd))
        else:
            params.append(p)
    return net.model_copy(update={"params": params})


def _new_rows(cand: ModelFit, before: Network | None) -> list[dict[str, Any]]:
    """The estimate rows (value, standard error, status; SI) of the parameters ``cand`` has and ``before`` lacks."""
    old = set(before.param_names) if before is not None else set()
    est = (cand.trained.meta.get("estimation") or {}) if cand.trained is not None else {}
    keep = ("name", "estimate", "se", "status", "unit")
    return [{k: r.get(k) for k in keep} for r in est.get("rows") or []
            if r.get("kind") == "parameter" and r.get("name") not in old]


def with_ml_values(params: dict[str, np.ndarray], cand: ModelFit) -> dict[str, np.ndarray]:
    """A copy of the doctor's numpy parameter dict ``params`` with the likelihood fit's scalar constants (same name,
    both scalar) put in; initial states (``x0:…``) and a learned function's weights (another layout) are kept."""
    out = {k: np.array(v, copy=True) for k, v in params.items()}
    for k, v in (cand.trained.params if cand.trained is not None else {}).items():
        if k in out and not k.startswith(X0_PREFIX) and np.ndim(out[k]) == 0 and np.size(v) == 1:
            out[k] = np.asarray(float(np.asarray(v).reshape(-1)[0]), dtype=np.float64)
    return out


def likelihood_summary(fit: ModelFit) -> dict[str, Any]:
    """What the baseline and the extension report of a likelihood fit."""
    return {"loglik": fit.loglik, "k": fit.k, "n_obs": fit.n_obs, "aic": fit.aic, "bic": fit.bic,
            "converged": fit.converged, "one_step_rms_val": fit.one_step_rms}
