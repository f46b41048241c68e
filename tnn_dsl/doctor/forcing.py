"""Score-test columns of the structural candidates on a fixed trajectory: the extra heat flows of a thermal
mass (:func:`mass_forcing`, with its grid of own time constants) and the lagged heat of a source with a
capacity behind it (:func:`source_lag_forcing`, exact at fixed τ). Derivations in the docstrings."""

from __future__ import annotations

import math

import numpy as np

from ..ir import (
    Network,
)
from .base import Candidate, refs_in, temps_in

__all__ = ["mass_forcing", "mass_grid", "source_lag_forcing", "source_tau_grid"]


def _series(net: Network, expr, U: np.ndarray, params: dict, X: np.ndarray, state_names, depth: int = 0) -> np.ndarray:
    """An expression of the network evaluated over samples: ``U (N, ≥ n_in)`` SI inputs in ``net.inputs`` order,
    ``X (N, n_states)`` K, ``params`` the numpy constants (derived parameters are evaluated recursively)."""
    from ..compiler import evaluate_expr as evaluate

    if depth > 64:
        raise ValueError("parameter expressions nest too deep (a cycle?)")
    n = U.shape[0]
    inputs = net.input_names
    values, temps = {}, {}
    for r in refs_in(expr):
        if r in inputs:
            values[r] = U[:, inputs.index(r)]
        elif r in params:
            values[r] = np.asarray(params[r], dtype=float)
        else:
            values[r] = _series(net, net.param(r).expr, U, params, X, state_names, depth + 1)
    for t in temps_in(expr):
        if t in state_names:
            temps[t] = X[:, list(state_names).index(t)]
        else:
            bnd = next(bd for bd in net.boundaries if bd.name == t)
            temps[t] = _series(net, net.param(bnd.temperature).expr, U, params, X, state_names, depth + 1)
    return np.broadcast_to(np.asarray(evaluate(expr, np, values, temps), dtype=float), (n,)).copy()


def mass_forcing(net: Network, cand: Candidate, X: np.ndarray, U: np.ndarray, params: dict, lengths, dts,
                 frac: float = 0.5, rates: np.ndarray | None = None, mass: float | None = None) -> np.ndarray:
    """The effect of a ``thermal_mass`` candidate on the current trajectory as extra heat flows into the nodes,
    W per J/K of ``C_m``: shape ``(N, n_nodes)`` in ``net.nodes`` order (the forcing inputs' order). With
    ``mass=None`` the first-order term (the limit ``C_m → 0``); with ``mass = C`` (J/K) the flows a mass ``C``
    causes on this trajectory, divided by ``C`` (so a least-squares fit of the resulting output column is
    ``C_m`` in J/K either way).

    Derivation. The link a–b (total resistance R) is split at a node m: ``R1 = f·R`` on a's side,
    ``R2 = (1−f)·R`` on b's. m's balance ``C_m·dT_m/dt = (T_a − T_m)/R1 + (T_b − T_m)/R2``, i.e.
    ``τ·dT_m/dt = T_m0 − T_m`` with ``T_m0 = (R2·T_a + R1·T_b)/R = (1−f)·T_a + f·T_b`` and ``τ = C_m·f(1−f)·R``.
    The heat into a is ``(T_m − T_a)/R1 = (T_b − T_a)/R + (T_m − T_m0)/R1`` — the unsplit link's flow plus
    ``(T_m − T_m0)/R1 = −τ·(dT_m/dt)/R1 = −C_m·(1−f)·dT_m/dt``; likewise ``−C_m·f·dT_m/dt`` into b (together the
    heat the mass stores). At ``C_m → 0`` m is quasi-static, ``T_m = T_m0``: the first-order term is
    ``−C_m·(1−f)·dT_m0/dt`` into a, ``−C_m·f·dT_m0/dt`` into b, with ``dT_m0/dt = (1−f)·dT_a/dt + f·dT_b/dt``.
    With a finite ``C`` ``T_m`` is ``T_m0`` through the first-order lag τ, computed exactly on the sampled
    trajectory (``T_m0`` linear within a sample for nodes, held for boundaries under zero-order-hold inputs);
    the network's response to the changed flows is left to the caller's linearised simulation.

    The score test holds each sample's forcing over the sample interval, so the rates are interval means,
    ``(T_m[k+1] − T_m[k])/dt``: exact for the lagged ``T_m``; in the limit, a node's ``(X[k+1] − X[k])/dt``
    (``X[k] + dt·rates[k]`` stands in for the sample after a file's last) and a boundary's impulse at ``k·dt``,
    ``(T_b[k] − T_b[k−1])/dt`` (0 on a file's first sample: it starts at steady state). ``X (N, n_states)`` K and
    ``U (N, ≥ n_in)`` SI are the concatenated files of ``lengths`` samples and steps ``dts`` (s); ``params``
    the numpy parameter values (the split link's value ``P`` is read there)."""
    from scipy.signal import lfilter

    el = cand.element
    a, b = el["a"], el["b"]
    nodes = net.node_names
    n = X.shape[0]
    bounds = np.cumsum([0] + [int(x) for x in lengths])
    if bounds[-1] != n:
        raise ValueError(f"file lengths sum to {bounds[-1]}, states have {n} rows")
    dt_row = np.concatenate([np.full(int(k), float(d)) for k, d in zip(lengths, dts)]) if n else np.zeros(0)

    def start_end(v: str) -> tuple[np.ndarray, np.ndarray]:
        """v's temperature at the start of each sample interval (after a held input's jump) and at its end."""
        if v in nodes:
            x = X[:, nodes.index(v)]
            end = np.empty(n)
            for s0, s1 in zip(bounds[:-1], bounds[1:]):
                if s1 <= s0:
                    continue
                end[s0: s1 - 1] = x[s0 + 1: s1]
                last = rates[s1 - 1, nodes.index(v)] if rates is not None else (
                    (x[s1 - 1] - x[s1 - 2]) / dt_row[s1 - 1] if s1 - s0 >= 2 else 0.0)
                end[s1 - 1] = x[s1 - 1] + dt_row[s1 - 1] * last
            return x, end
        bnd = next(bd for bd in net.boundaries if bd.name == v)
        tb = _series(net, net.param(bnd.temperature).expr, U, params, X, nodes)
        return tb, tb

    (a0, a1), (b0, b1) = start_end(a), start_end(b)
    p0 = (1.0 - frac) * a0 + frac * b0  # T_m0 at the start of each interval
    p1 = (1.0 - frac) * a1 + frac * b1  # ... and at its end
    rate = np.empty(n)
    if mass is None:  # quasi-static: T_m = T_m0 at the interval ends (continuous); steady start
        for s0, s1 in zip(bounds[:-1], bounds[1:]):
            if s1 <= s0:
                continue
            prev = np.concatenate([[p0[s0]], p1[s0: s1 - 1]])
            rate[s0:s1] = (p1[s0:s1] - prev) / dt_row[s0:s1]
    else:
        el_v = float(np.asarray(params[el["value"]]).reshape(-1)[0]) if el["value"] in params else float(
            net.param(el["value"]).value)
        r_tot = el_v if el["form"] == "R" else 1.0 / el_v
        tau = float(mass) * frac * (1.0 - frac) * r_tot
        for s0, s1 in zip(bounds[:-1], bounds[1:]):
            if s1 <= s0:
                continue
            h = float(dt_row[s0])  # one step per file
            e = math.exp(-h / tau)
            # exact step of τ·dT/dt = p(t) − T with p linear from p0 to p1 over h:
            # T(h) = p1 − (p1 − p0)·τ/h + (T(0) − p0 + (p1 − p0)·τ/h)·e^(−h/τ) = e·T(0) + c
            slope_tau = (p1[s0:s1] - p0[s0:s1]) * tau / h
            c = p1[s0:s1] - slope_tau - (p0[s0:s1] - slope_tau) * e
            out = np.empty(s1 - s0 + 1)
            out[0] = p0[s0]  # steady start
            out[1:] = lfilter([1.0], [1.0, -e], c, zi=[e * out[0]])[0]
            rate[s0:s1] = np.diff(out) / h
    F = np.zeros((n, len(nodes)))
    F[:, nodes.index(a)] = -(1.0 - frac) * rate
    if b in nodes:
        F[:, nodes.index(b)] = -frac * rate
    return F


def mass_grid(net: Network, cand: Candidate, params: dict, dt: float, duration: float, frac: float = 0.5,
              step: float = 3.0) -> list[float]:
    """Capacities (J/K) at which the score test tries a thermal mass beyond first order: its own time constant
    ``C·f(1−f)·R`` from half a sample to a third of the data's ``duration`` (s) in factors of ``step``, and at
    most 100 × the larger capacity of the link's nodes. At first order a mass on a link to a constant boundary
    is exactly a larger capacity of the node (``−C_m(1−f)²·dT_a/dt``); only its lag tells them apart."""
    el = cand.element
    v = float(np.asarray(params[el["value"]]).reshape(-1)[0]) if el["value"] in params else float(
        net.param(el["value"]).value)
    r_tot = v if el["form"] == "R" else 1.0 / v
    per_tau = 1.0 / (frac * (1.0 - frac) * r_tot)  # C per second of τ
    caps = []
    for nd in net.nodes:
        if nd.name in (el["a"], el["b"]):
            c = params.get(nd.capacitance)
            c = float(np.asarray(c).reshape(-1)[0]) if c is not None else net.param(nd.capacitance).value
            if c and c > 0:
                caps.append(float(c))
    c_max = 100.0 * max(caps) if caps else math.inf
    out, tau = [], 0.5 * dt
    while tau <= duration / 3.0 and tau * per_tau <= c_max:
        out.append(tau * per_tau)
        tau *= step
    return out


def _value_series(net: Network, pname: str, U: np.ndarray, params: dict, X: np.ndarray) -> np.ndarray:
    """Parameter ``pname`` over the samples (a constant broadcast, or its expression evaluated)."""
    n = U.shape[0]
    if pname in params:
        return np.broadcast_to(np.asarray(params[pname], dtype=float).reshape(-1)[:1], (n,)).copy()
    return _series(net, net.param(pname).expr, U, params, X, net.node_names)


def _lag_means(x: np.ndarray, h: float, tau: float, y0: float) -> np.ndarray:
    """Interval means of ``y`` with ``τ·dy/dt = x − y``, ``x`` held over each interval of ``h`` s, ``y(0) = y0``."""
    from scipy.signal import lfilter

    e = math.exp(-h / float(tau))
    y = lfilter([1.0 - e], [1.0, -e], x, zi=[e * y0])[0]  # y at the end of each interval
    y_start = np.concatenate([[y0], y[:-1]])
    return x + (y_start - x) * (float(tau) / h) * (1.0 - e)


def source_lag_forcing(net: Network, cand: Candidate, X: np.ndarray, U: np.ndarray, params: dict, lengths, dts,
                       tau: float, rates: np.ndarray | None = None) -> np.ndarray:
    """The change of the heat flows into the nodes (W, shape ``(N, n_nodes)`` in ``net.nodes`` order) when the
    ``source_mass`` candidate's source reaches its node through a capacity ``C_h`` behind a resistance ``R_h``
    with ``τ = C_h·R_h = tau`` (s): with ``rates=None`` the lag part, else the part per J/K of ``C_h``.

    Derivation. The heat into node n is ``Q_h = (T_h − T_n)/R_h``; with ``T_h = T_n + R_h·Q_h`` the new node's
    balance ``C_h·dT_h/dt = Q − Q_h`` is ``τ·dQ_h/dt = Q − Q_h − C_h·dT_n/dt``, so on a given trajectory
    ``Q_h − Q = [lag_τ(Q) − Q] − C_h·lag_τ(dT_n/dt)``: at fixed τ exactly linear in ``C_h`` — the lag part (its
    coefficient 1 for the whole source behind the capacity) and the capacity part (``−lag_τ(dT_n/dt)`` per J/K,
    ``rates (N, n_states)`` K/s the nodes' rates over each sample interval). ``Q`` and the rates are held over
    each sample (zero-order hold), the lag starts at steady state (``Q_h = Q``, ``dT_n/dt = 0``) and is
    integrated exactly; the forcing returned is the interval mean. ``X (N, n_states)`` K and ``U (N, ≥ n_in)``
    SI are the concatenated files of ``lengths`` samples and steps ``dts`` (s)."""
    el = cand.element
    nodes = net.node_names
    n = U.shape[0]
    bounds = np.cumsum([0] + [int(x) for x in lengths])
    if bounds[-1] != n:
        raise ValueError(f"file lengths sum to {bounds[-1]}, inputs have {n} rows")
    at = nodes.index(el["at"])
    x_all = _value_series(net, el["value"], U, params, X) if rates is None else np.asarray(rates)[:, at]
    col = np.zeros(n)
    for s0, s1, h in zip(bounds[:-1], bounds[1:], dts):
        if s1 <= s0:
            continue
        x = x_all[s0:s1]
        if rates is None:
            col[s0:s1] = _lag_means(x, float(h), tau, float(x[0])) - x
        else:
            col[s0:s1] = -_lag_means(x, float(h), tau, 0.0)
    F = np.zeros((n, len(nodes)))
    F[:, at] = col
    return F


def source_tau_grid(dt: float, duration: float, step: float = 3.0) -> list[float]:
    """Time constants (s) at which the score test tries a lag behind a source: half a sample to a third of the
    data's ``duration`` (s), in factors of ``step``."""
    out, tau = [], 0.5 * float(dt)
    while tau <= duration / 3.0:
        out.append(tau)
        tau *= step
    return out
