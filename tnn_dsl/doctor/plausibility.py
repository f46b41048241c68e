"""Is a fitted candidate physical? Its values judged against the network's own scales and its simulated
temperatures against the data's.

A least-squares fit takes any values that lower the error: a heat capacity behind a source of 0.004 J/K joined
by 8000 K/W is, to the data, a first-order lag on the source — and a node 6000 K above the board. The doctor
accepts only candidates whose

* **capacities and resistances** (every constant capacity, resistance and conductance of the fitted network,
  conductances read as resistances) lie within :data:`DECADES` decades of the range the user wrote in the
  network (its own node capacities and link values), and whose
* **temperatures** (every node and sensor-lag state of the fitted model's free runs over training and held-out
  data) stay within the data's temperature range (sensor readings and temperature inputs) widened by
  :data:`MARGIN_K` or half that range, whichever is larger (a node a source heats and no sensor reads may run
  up to :data:`HEATED_MARGIN_K` above the hottest reading: a heater's element);

a fit whose simulation is not finite, or leaves the data's range by orders of magnitude, has *diverged*.
:func:`judge` says which, with the reason in the network's terms."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..ir import Network

__all__ = ["DECADES", "MARGIN_K", "HEATED_MARGIN_K", "Scales", "network_scales", "judge", "start_up_rows"]

DECADES = 3.0
"""How many decades beyond the network's own capacities and resistances a fitted one may lie."""

MARGIN_K = 20.0
"""Smallest margin (K) around the data's temperature range within which simulated temperatures must stay."""

HEATED_MARGIN_K = 500.0
"""Margin (K) above the data's hottest temperature for a node a source heats directly and no sensor reads: a
heater's element runs far hotter than the room it heats (Bacher & Madsen's heater node), but not thousands of
kelvin hotter."""

DIVERGED_FACTOR = 1000.0
"""A simulated temperature this many data ranges (a range of at least 10 K) outside the data's range: the fit
diverged."""


@dataclass(frozen=True)
class Scales:
    """The plausible ranges of one diagnosis: capacity (J/K), resistance (K/W) and temperature (K), each
    ``(low, high)``; ``None`` where the network gives no scale."""

    capacity: tuple[float, float] | None
    resistance: tuple[float, float] | None
    temperature: tuple[float, float] | None
    data_range: tuple[float, float] | None
    margin: float = MARGIN_K
    """K by which ``data_range`` is widened into ``temperature`` (and a state's current range, in :func:`judge`)."""


def _values(net: Network, params: dict | None = None) -> tuple[dict[str, float], dict[str, float]]:
    """``({capacity param: J/K}, {link param: K/W})`` of the constant, positive capacities and link values of
    ``net`` (from ``params`` where given, else as written)."""

    def value(name: str) -> float | None:
        try:
            p = net.param(name)
        except KeyError:
            return None
        if not p.is_constant:
            return None
        if params is not None and name in params:
            v = float(np.asarray(params[name]).reshape(-1)[0])
        else:
            v = p.value
        return float(v) if v is not None and math.isfinite(v) and v > 0 else None

    learned = net.learned_targets()
    caps = {n.capacitance: v for n in net.nodes if n.capacitance not in learned
            for v in [value(n.capacitance)] if v is not None}
    res = {}
    for link in net.links:
        if link.value in learned:
            continue
        v = value(link.value)
        if v is not None:
            res[link.value] = v if link.form == "R" else 1.0 / v
    return caps, res


def network_scales(net: Network, experiments) -> Scales:
    """The ranges of ``net`` as written and of the data ``experiments`` (outputs and temperature inputs, K)."""
    caps, res = _values(net)
    f = 10.0 ** DECADES

    def span(vals):
        return (min(vals) / f, max(vals) * f) if vals else None

    temps = []
    t_inputs = [j for j, i in enumerate(net.inputs) if i.dim == {"K": 1}]
    for e in experiments:
        y = np.asarray(e.outputs, dtype=float)
        temps.append(y[np.isfinite(y)])
        if t_inputs:
            u = np.asarray(e.inputs, dtype=float)[:, t_inputs]
            temps.append(u[np.isfinite(u)])
    allt = np.concatenate(temps) if temps else np.zeros(0)
    if allt.size:
        lo, hi = float(allt.min()), float(allt.max())
        m = max(MARGIN_K, 0.5 * (hi - lo))
        trange, drange = (lo - m, hi + m), (lo, hi)
    else:
        trange, drange, m = None, None, MARGIN_K
    return Scales(span(list(caps.values())), span(list(res.values())), trange, drange, m)


def _fmt(v: float, unit: str) -> str:
    return f"{v:.3g} {unit}"


def judge(net: Network, params: dict, states: np.ndarray, state_names, scales: Scales,
          temperature_unit: str = "K", before: dict | None = None,
          current: dict[str, tuple[float, float]] | None = None,
          start: np.ndarray | None = None) -> tuple[str, str | None]:
    """``(verdict, reason)`` of a fitted network ``net`` with numpy ``params`` whose free runs gave ``states
    (N, n_states)`` K: ``("ok", None)``, ``("diverged", why)`` or ``("non-physical", why)``.
    ``temperature_unit`` is the file's (``degC`` temperatures are written in °C in the reason). ``before``: the
    current model's numpy parameters; a value already outside its range there is not held against a candidate
    (the baseline's own drift is reported separately). ``current``: each state's (min, max) K in the current
    model's free runs; a state may go where the current model already goes (a Peltier's cold side far below the
    one sensor's readings is the network's, not the candidate's), widened by the same margin. ``start``: a mask
    ``(N, n_states)`` of each file's start-up samples, not held to the temperature ranges (a fitted initial state of
    a node no sensor sees is a nuisance, not a claim of the candidate: it decays within a few of its time
    constants; :func:`start_up_rows`)."""

    def temp(v: float) -> str:
        return f"{v - 273.15:.4g} °C" if temperature_unit == "degC" else f"{v:.4g} K"

    X = np.asarray(states, dtype=float)
    if not np.all(np.isfinite(X)):
        return "diverged", "its simulation is not finite (the fitted values leave the range where it is stable)"
    names = list(state_names)
    if start is not None and start.shape == X.shape:
        X = np.where(start, np.nan, X)
    if scales.data_range is not None and X.size and np.isfinite(X).any():
        lo, hi = scales.data_range
        far = DIVERGED_FACTOR * max(hi - lo, 10.0)
        xmax, xmin = float(np.nanmax(X)), float(np.nanmin(X))
        if xmax > hi + far or xmin < lo - far:
            return "diverged", (f"its simulation runs away ({temp(xmax if xmax > hi + far else xmin)}"
                                f" against data within {temp(lo)} … {temp(hi)})")
    reasons = []
    caps, res = _values(net, params)
    caps0, res0 = _values(net, before) if before is not None else ({}, {})
    f = 10.0 ** DECADES
    for values, values0, rng, unit, what in ((caps, caps0, scales.capacity, "J/K", "capacities"),
                                            (res, res0, scales.resistance, "K/W", "resistances")):
        if rng is None:
            continue
        lo, hi = rng
        for k, v in values.items():
            if lo <= v <= hi or (k in values0 and not lo <= values0[k] <= hi):
                continue  # in range, or already out of range in the current model (not this candidate's doing)
            reasons.append(f"{k} = {_fmt(v, unit)}{' (as a resistance)' if unit == 'K/W' else ''} is more than "
                           f"{DECADES:g} decades {'below' if v < lo else 'above'} the network's {what} "
                           f"({_fmt(lo * f, unit)} … {_fmt(hi / f, unit)})")
    if scales.temperature is not None and X.size:
        lo, hi = scales.temperature
        sensed = {s.node for s in net.sensors}
        heated = {src.node for src in net.sources} - sensed
        for j, n in enumerate(names):
            x = X[:, j][np.isfinite(X[:, j])]
            if not x.size:
                continue
            lo_j, hi_j = lo, hi
            if n in heated and scales.data_range is not None:
                hi_j = max(hi_j, scales.data_range[1] + HEATED_MARGIN_K)
            if current and n in current:
                lo_j, hi_j = min(lo_j, current[n][0] - scales.margin), max(hi_j, current[n][1] + scales.margin)
            if float(x.max()) > hi_j or float(x.min()) < lo_j:
                v = float(x.max()) if float(x.max()) > hi_j else float(x.min())
                what = f"node {n}" if not n.endswith(".lag") else f"the lag state of sensor {n[:-4]}"
                d0, d1 = scales.data_range or (lo, hi)
                reasons.append(f"{what} reaches {temp(v)} (the data lie within {temp(d0)} … {temp(d1)})")
    if reasons:
        return "non-physical", "; ".join(reasons[:3]) + (f" (and {len(reasons) - 3} more)" if len(reasons) > 3 else "")
    return "ok", None


def start_up_rows(n_steps: list[int], dts: list[float], taus: dict[str, float], state_names) -> np.ndarray:
    """``(N, n_states)`` mask of each file's start-up samples: for state j, the first ``5·τ_j/dt`` samples of every
    file (at most a tenth of it), ``τ_j`` its time constant (s) at the fitted values."""
    names = list(state_names)
    out = np.zeros((int(sum(n_steps)), len(names)), dtype=bool)
    r0 = 0
    for n, dt in zip(n_steps, dts):
        for j, name in enumerate(names):
            tau = taus.get(name, 0.0)
            k = min(int(math.ceil(5.0 * tau / dt)) if math.isfinite(tau) and dt > 0 else n // 10, n // 10)
            out[r0: r0 + k, j] = True
        r0 += n
    return out
