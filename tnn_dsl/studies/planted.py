"""Hidden-effect data for testing the model doctor: simulate a network with ONE planted deficiency.

The truth is the network's IR plus one edit of a known kind (``_candidates``) set to a non-null value:
a parameter that depends on an input or a temperature, a heat load, a missing link, radiation, a sensor
offset, a wrong constant. Data are simulated with the compiled model (RK4) from the steady state of the
first inputs, sensor noise added; the diagnosis sees only the original network and the data.

Used by ``tests/test_diagnose*.py`` and ``benchmarks/diagnose_suite.py``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..data import Experiment
from ..doctor import STRUCTURAL_KINDS, Candidate, apply_structural, build_extended, structural_candidates
from ..ir import Network

__all__ = ["Planted", "step_inputs", "plant", "find_candidate"]


@dataclass
class Planted:
    """The planted truth and its data. ``candidate`` is the truth's edit; ``value`` its column values."""

    candidate: Candidate | None
    values: list[float]
    train: list[Experiment]
    val: list[Experiment]


def step_inputs(rng: np.random.Generator, n: int, bounds: dict[str, tuple[float, float]], names, hold=(60, 300)):
    """Pseudo-random step sequences ``(n, len(names))`` (SI): hold times uniform in ``hold`` samples, levels
    uniform in each input's ``bounds`` (an input absent from ``bounds`` is held at 0)."""
    u = np.zeros((n, len(names)))
    for j, name in enumerate(names):
        lo, hi = bounds.get(name, (0.0, 0.0))
        k = 0
        while k < n:
            h = int(rng.integers(hold[0], hold[1] + 1))
            u[k: k + h, j] = rng.uniform(lo, hi)
            k += h
    return u


def find_candidate(cands: list[Candidate], kind: str, target: str, depends_on: str | None = None) -> Candidate:
    for c in cands:
        if c.kind == kind and c.target == target and ((depends_on is None and not c.depends_on)
                                                       or (depends_on is not None and c.depends_on == [depends_on])):
            return c
    raise KeyError(f"no candidate {kind} {target} {depends_on}; have e.g. "
                   + ", ".join(c.key for c in cands[:12]))


def plant(net: Network, bounds: dict[str, tuple[float, float]], kind: str | None, target: str | None = None,
          depends_on: str | None = None, strength: float = 0.3, *, n_train: int = 2400, n_val: int = 1200,
          dt: float = 1.0, noise: float = 0.0, seed: int = 0, backend: str = "jax",
          hold: tuple[int, int] = (60, 300)) -> Planted:
    """Simulate ``net`` with one planted effect (``kind=None``: the nominal network, a null data set).

    ``strength`` is the effect's size in the candidate's own coordinates: a relative change of the
    parameter at the edge of the variable's range (dependence), the raw output for a wrong constant or a
    heat load (in units of the function's output scale), W/K for a missing link, m² (ε·A) for radiation,
    K for a sensor offset, seconds for a sensor lag (``kind="sensor_lag"``, ``target`` the sensor), J/K for a
    thermal mass, seconds for a heat capacity behind a source (``kind="source_mass"``, ``target`` the source: its
    time constant C_h·R_h, with C_h a quarter of the heated node's capacity). Returns training and validation
    :class:`Experiment` objects (different seeds).
    """
    from ..compiler import compile as _compile
    from ..doctor import normalisation_stats

    rng_tr = np.random.default_rng(1000 + seed)
    rng_va = np.random.default_rng(2000 + seed)
    names = net.input_names
    u_tr = step_inputs(rng_tr, n_train, bounds, names, hold)
    u_va = step_inputs(rng_va, n_val, bounds, names, hold)
    varying = [n for n in names if n in bounds and bounds[n][1] > bounds[n][0]]
    cand = None
    if kind in STRUCTURAL_KINDS:  # not exactly null: the truth is the network with the edit built in
        cand = find_candidate(structural_candidates(net, (kind,)), kind, target, depends_on)
        if kind == "source_mass":  # strength: the lag τ (s); C_h a quarter of the heated node's capacity
            node = next(nd for nd in net.nodes if nd.name == cand.element["at"])
            cap = 0.25 * float(net.param(node.capacitance).value)
            net = apply_structural(net, cand, cap, resistance=strength / cap)
        else:
            net = apply_structural(net, cand, strength)
        kind = None
    ext = build_extended(net, varying)
    model = _compile(ext.network, backend=backend, dtype="float64")
    p = model.to_numpy(model.init_params(0))
    values: list[float] = [strength] if cand is not None else []

    def run(params, u):
        T0 = model.steady_state(model.from_numpy(params), np.asarray(u[0]))
        st, y = model.rollout(model.from_numpy(params), T0, np.asarray(u), dt)
        return np.asarray(model.xp.to_numpy(st)), np.asarray(model.xp.to_numpy(y))

    st, _ = run(p, u_tr)
    p = normalisation_stats(model, p, ext.fn_vars, ext.network, u_tr, st, np.ones(n_train, bool), dt=dt)
    if kind is not None:
        cand = find_candidate(ext.candidates, kind, target, depends_on)
        col = cand.columns[0]
        arr = np.array(p[col.key], dtype=float)
        flat = arr.reshape(-1)
        flat[col.index] = strength
        p[col.key] = flat.reshape(arr.shape)
        values = [strength] + [0.0] * (cand.k - 1)
    out = []
    for u, rng in ((u_tr, np.random.default_rng(3000 + seed)), (u_va, np.random.default_rng(4000 + seed))):
        _, y = run(p, u)
        if noise > 0:
            y = y + rng.normal(0.0, noise, y.shape)
        n = u.shape[0]
        out.append(Experiment(name=f"planted-{kind}-{seed}", path="<planted>", t=np.arange(n) * dt, dt=dt,
                              inputs=u, outputs=y, input_names=tuple(names),
                              output_names=tuple(s.name for s in net.sensors)))
    return Planted(cand, values, [out[0]], [out[1]])
