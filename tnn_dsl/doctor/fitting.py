"""Proper fits of shortlisted candidates (Levenberg–Marquardt on the engine, structural candidates on their own
network) and their held-out numbers."""

from __future__ import annotations

import math
import time as _time
from typing import Iterable

import numpy as np
from scipy import stats

from ..analysis import held_out_test as _held_out_test
from ..analysis import residuals as R
from ..ir import Network
from .base import Candidate, Extended
from .candidates import build_extended
from .engine import FIT_ITER_FIRST, _alias, _Engine, _make_engine
from .stopping import stop_requested
from .structural import apply_structural


def written_values(eng: _Engine, params: dict, names: list[str], learned: Iterable[str] = ()) -> dict | None:
    """``params`` with the free constants ``names`` put back at the values written in the file (``eng.params0``),
    and the fitted arrays (the engine's columns) of the learned functions ``learned`` (the user's ``learn`` clauses,
    by function name) at their initial values, where every target equals its written nominal value; ``None`` when
    none of the constants is in the engine."""
    p = {k: np.array(v, copy=True) for k, v in params.items()}
    n = 0
    for name in names:
        kk = _alias(name, p)
        if kk is not None and kk in eng.params0:
            p[kk] = np.array(eng.params0[kk], dtype=float, copy=True)
            n += 1
    if not n:
        return None
    own = set(learned)
    for key in {c.key for c in eng.cols if c.key.split(".", 1)[0] in own} if own else ():
        if key in eng.params0 and key in p:
            p[key] = np.array(eng.params0[key], dtype=float, copy=True).reshape(p[key].shape)
    return p


def continue_fit(eng: _Engine, act: list[int], info: dict, max_iter: int, deadline, tol: float,
                 stall: bool = False) -> dict:
    """A fit (``info``) that stopped at its Jacobian cap still moving, continued from ``eng.params`` to ``max_iter``
    Jacobians in all, its counts summed; ``info`` itself when it converged or had them all (successive halving's
    second stage: :func:`refit_from_written`, the extended model's two starts in ``session.second_start``)."""
    if not (info["capped"] and max_iter > info["jacobians"]):
        return info
    more = eng.fit(act, max_iter=max_iter - info["jacobians"], deadline=deadline, tol=tol, stall=stall)
    return {**more, "iterations": info["iterations"] + more["iterations"],
            "jacobians": info["jacobians"] + more["jacobians"]}


def refit_from_written(eng: _Engine, act: list[int], info: dict, start: dict, names: list[str], max_iter: int,
                       deadline, say, learned: Iterable[str] = ()) -> dict:
    """After a fit from ``start`` (``info``, ``eng.params`` its result): the same fit again from ``start`` with the
    free constants ``names`` at the values written in the file (the fit so far moved them far:
    :func:`tnn_dsl.doctor.session._moved`) and the user's learned functions ``learned`` at their written nominal
    values (:func:`written_values`); the lower training SSE wins and is left in ``eng.params``. Returns the
    winner's info (``"start": "written"`` when the second start won). The compensation of the baseline is a basin
    the candidate's fit may not leave: a 0.3 K offset of the case study's only sensor drove ``pe.resistance`` to the
    edge of its prior range (−99 %) and ``pe.seebeck`` −41 %, and every candidate fitted from there, the offset too,
    stayed in it (suite case ``casestudy/sensor_offset``). The user's learned functions go back too: M1's ``learn
    R_hp1, R_hp2, R_hpa as const`` had absorbed the missing u1 law in the baseline fit (``R_hp2`` 0.2 → 0.0074 K/W),
    and with only the Peltier's constants reset the three resistances depending on u1 converged at a training SSE
    of 1.24 K² with ``R_hp2`` still 0.0074 K/W; from the written resistances they reach 0.33 K² after four
    Jacobians, the three near the truth's values and slopes (the case study's 4 h, 2026-12-03; BENCHMARKS.md).

    Successive halving between the two starts: the second one gets :data:`FIT_ITER_FIRST` Jacobians first and goes
    on to ``max_iter`` only if its training SSE is then below the first start's (on the case study's 4 h, a probe's
    second start had crawled to its cap of 80 Jacobians, 12 s, and lost: 184.8 against 138.9 K²)."""
    start = written_values(eng, start, names, learned) if names else None
    if start is None or stop_requested() or (deadline is not None and _time.monotonic() > deadline):
        return info
    first = eng.params
    eng.params = start
    t_f = _time.monotonic()
    info_w = eng.fit(act, max_iter=min(max_iter, FIT_ITER_FIRST), deadline=deadline, tol=1e-4, stall=True)
    if info_w["sse"] < info["sse"]:
        info_w = continue_fit(eng, act, info_w, max_iter, deadline, 1e-4, stall=True)
    say(f"    fitted again from the written values in {_time.monotonic() - t_f:.1f} s ({info_w['iterations']} "
        f"iterations, {info_w['jacobians']} Jacobians; training SSE {info_w['sse']:.4g} against {info['sse']:.4g} K²)")
    if info_w["sse"] < info["sse"]:
        return {**info_w, "start": "written"}
    eng.params = first
    return info


def _fit_structural(c: Candidate, s_: dict, net_x: Network, varying, extra, kinds, acc_keys, exps, train_mask, val_mask,
                    backend, state, ref, dt_min, deadline, e_base_val, say, delta=None) -> dict | None:
    """Fit a structural (not exactly null) candidate on its own network: the base network with the edit
    built in (:func:`apply_structural`), started from the score test's Gauss–Newton value.

    A thermal mass starts at the Gauss–Newton ``C_m`` (J/K) clipped to ``[max(4·dt/R, 10⁻³·C_min), 100·C_max]``
    (``R`` the split link's total resistance, so that the new node's time constant ``C_m·f(1−f)·R`` is at least
    one sample at f = 1/2; ``C_min``/``C_max`` the capacities of the link's nodes) and is bounded below by
    ``0.4·dt/R`` (a tenth of a sample); ``f`` starts at 1/2.

    A heat capacity behind a source starts at the score test's lag ``τ`` (the grid value whose two columns
    explained most, times the Gauss–Newton amplitude of the lag column, clipped to [0.2, 5]) and at the
    Gauss–Newton ``C_h`` of the capacity column (clipped to [10⁻³, 10] × the heated node's capacity; a tenth of
    it if not positive), ``R_h = τ/C_h``; ``C_h`` is bounded below by 10⁻⁴ of that capacity, ``R_h`` by
    ``0.05·dt/C_h``.

    ``delta`` replaces the score test's Gauss–Newton values as the start (the likelihood objective fits a lag or a
    mass whose linearised output-error fit wants a negative value from the smallest start instead). It is not fitted
    a second time from the written values of constants the fit moved far (:func:`refit_from_written`): on the case
    study's planted thermal masses both starts reached the same training SSE."""
    delta = s_["delta"] if delta is None else delta
    t0 = float(delta[0]) if len(delta) else 0.0
    frac = 0.5
    if c.kind == "sensor_lag":
        if not t0 > 0:
            say("    the linearised fit wants a negative lag: not fitted")
            return None
        t0 = float(np.clip(t0, 0.5 * dt_min, 1e4 * dt_min))
        lower = 0.2 * dt_min
    elif c.kind == "thermal_mass":
        if not t0 > 0:
            say("    the linearised fit wants a negative thermal mass: not fitted")
            return None
        el = c.element
        v = float(net_x.param(el["value"]).value)
        r_tot = v if el["form"] == "R" else 1.0 / v
        caps = []
        for n in net_x.nodes:
            if n.name in (el["a"], el["b"]):
                pc = net_x.param(n.capacitance)
                if pc.is_constant and pc.value and pc.value > 0:
                    caps.append(float(pc.value))
        lo = 4.0 * dt_min / r_tot
        hi = 100.0 * max(caps) if caps else 1e6 * lo
        if caps:
            lo = max(lo, 1e-3 * min(caps))
        t0 = float(np.clip(t0, lo, max(hi, lo)))
        lower = 0.4 * dt_min / r_tot
    elif c.kind == "source_mass":
        if not t0 > 0:
            say("    the linearised fit wants a negative lag behind the source: not fitted")
            return None
        el = c.element
        tau = float(el.get("score_tau") or dt_min) * float(np.clip(t0, 0.2, 5.0))
        node = next(n for n in net_x.nodes if n.name == el["at"])
        pc = net_x.param(node.capacitance)
        c_node = float(pc.value) if pc.is_constant and pc.value and pc.value > 0 else None
        c_gn = float(delta[1]) if len(delta) > 1 else 0.0  # the capacity column's Gauss–Newton C_h
        if c_node:
            cap0 = float(np.clip(c_gn, 1e-3 * c_node, 10.0 * c_node)) if c_gn > 0 else 0.1 * c_node
        else:
            cap0 = c_gn if c_gn > 0 else max(tau, dt_min)  # J/K; without a known capacity: R_h = 1 K/W
        t0 = cap0
        lower = 1e-4 * c_node if c_node else None
        extra_kw = {"resistance": tau / cap0, "resistance_lower": 0.05 * dt_min / cap0}
    else:
        raise ValueError(f"not a structural candidate kind: {c.kind}")
    kw = {"frac": frac} if c.kind == "thermal_mass" else (extra_kw if c.kind == "source_mass" else {})
    net_s = apply_structural(net_x, c, t0, lower=lower, **kw)
    ext_s = build_extended(net_s, varying, extra, kinds=kinds, only=set(acc_keys))
    eng, x_s, f_s, c_s = _make_engine(ext_s, net_s, exps, train_mask, val_mask, backend, state, ref, acc_keys)
    act = list(f_s) + [j for k in acc_keys for j in c_s.get(k, [])]
    t_f = _time.monotonic()
    info = eng.fit(act, max_iter=15, deadline=deadline, tol=1e-4, stall=True)
    say(f"    fitted in {_time.monotonic() - t_f:.1f} s ({info['iterations']} iterations, {info['jacobians']} "
        "Jacobians, own network)")
    e_after = eng.residual()
    ev = np.where(eng.val_mask, e_after, np.nan)
    e1 = e_after.ravel()[eng.val_idx]
    F, pval, n_eff = _held_out_test(e_base_val, e1, c.k)
    val_sse = eng.sse(which="val")
    if c.kind in ("thermal_mass", "source_mass") and "states" in ref:
        # the reference run's states (learned-function normalisation, read by position) get the new node's
        # trajectory where it will sit if accepted: after the original nodes (lag states, never learn inputs,
        # shift). Of several masses fitted on one layout, the best-fitting one's column is kept.
        n0 = len(net_x.nodes)
        _, xs = eng.simulate()
        col = xs[:, list(eng.model.state_names).index(c.element["node"])]
        prev = ref.get("mass_col")
        st, names = np.asarray(ref["states"]), list(ref["names"])
        if prev is not None and prev["n0"] == n0 and st.shape[1] > n0:
            if val_sse < prev["sse"]:
                st = st.copy()
                st[:, n0] = col
                names[n0] = c.element["node"]
                ref["mass_col"] = {"n0": n0, "sse": val_sse}
        elif st.shape[1] >= n0:
            st = np.concatenate([st[:, :n0], col[:, None], st[:, n0:]], axis=1)
            names = names[:n0] + [c.element["node"]] + names[n0:]
            ref["mass_col"] = {"n0": n0, "sse": val_sse}
        ref["states"], ref["names"] = st, names
    return {"cand": c, "score": s_, "eng": eng, "ext": x_s, **_held_out_errors(ev), "e_val": e1, "val_sse": val_sse,
            "F": F, "p": pval, "n_eff": n_eff, "params": eng.params, "e_all": e_after, "net": net_s, "act": act}


def _fit_result(c: Candidate, s_: dict, eng: "_Engine", ext: Extended, e_base_val: np.ndarray) -> dict:
    """The held-out numbers of a candidate fitted on ``eng`` (its current parameters)."""
    e_after = eng.residual()
    ev = np.where(eng.val_mask, e_after, np.nan)
    e1 = e_after.ravel()[eng.val_idx]
    F, pval, n_eff = _held_out_test(e_base_val, e1, c.k)
    return {"cand": c, "score": s_, "eng": eng, "ext": ext, **_held_out_errors(ev), "e_val": e1,
            "val_sse": eng.sse(which="val"), "F": F, "p": pval, "n_eff": n_eff, "params": eng.params, "e_all": e_after,
            "net": None}


def _held_out_errors(ev: np.ndarray) -> dict:
    """``{"val_mae", "val_max"}`` (K) of the held-out residual ``ev`` (NaN off the held-out rows); NaN when the
    simulation gave no finite value there (a diverged fit)."""
    a = np.abs(ev[np.isfinite(ev)])
    if not a.size:
        return {"val_mae": math.nan, "val_max": math.nan}
    return {"val_mae": float(a.mean()), "val_max": float(a.max())}


def _train_lr_test(e0: np.ndarray, e1: np.ndarray, k: int, m: int) -> tuple[float, float]:
    """Likelihood-ratio test of the fitted candidate on the training rows: ``S = N_eff·ln(SSE0/SSE1)``
    against χ²(k), ``N_eff`` the extended model's residual sample size corrected for autocorrelation
    (:func:`tnn_dsl.analysis.residuals.effective_n`: under the alternative that residual is the noise). The
    candidate was picked among ``m`` scored ones, so its p is Bonferroni-corrected (×m). Returns
    ``(S, corrected p)``."""
    ok = np.isfinite(e0) & np.isfinite(e1)
    if ok.sum() < 8 or not np.all(np.isfinite(e1)):
        return 0.0, 1.0
    sse0, sse1 = float(e0[ok] @ e0[ok]), float(e1[ok] @ e1[ok])
    if not (sse1 > 0 and sse0 > sse1):
        return 0.0, 1.0
    S = R.effective_n(e1[ok]) * math.log(sse0 / sse1)
    return float(S), float(min(1.0, max(m, 1) * stats.chi2.sf(S, max(k, 1))))
