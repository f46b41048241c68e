"""Compile a :class:`~tnn_dsl.ir.network.Network` into a :class:`Model` on JAX, PyTorch (or numpy).

The model is the thesis's state-space form (eq. 2.4/2.10, written per node)

    C_i dT_i/dt = Σ_links g·(T_j − T_i) + Σ_radiation σεAF(T_j⁴ − T_i⁴) + Q_peltier + Q_fluid + Q_sources
                  + Q_learned,          τ_s dT_s/dt = T_node − T_s   (lagged sensors)

with parameters from the one flat table (``Network.params``) and learned functions (``_learned``).

How the per-step work is kept small (the design, in one place):

* Parameters are classified once: **static** (a constant, or derived only from constants) or **dynamic**
  (depends on an input, a node temperature or a learned function of them). Static values are computed
  once per call (``prepare``), dynamic ones every right-hand-side evaluation, in a topological order.
* All links with static conductance (and fluids with static ``ṁ cp (1 − a)`` and no learned flow) are
  pre-multiplied into one conductance matrix, so their whole contribution is one matmul ``T @ M``;
  constant boundaries and constant heat loads fold into a constant vector. Links and radiation with
  dynamic coefficients use gather/scatter matrices (two matmuls); point flows (Peltier sides, fluids,
  sources, learned heat loads) are stacked and scattered by one matmul.
* Learned-function inputs are gathered and normalised by matmuls with matrices prepared once.

Parameter-table keys: every constant parameter (``"C_ph"``), every learned array (``"f1.W0"``), and
optionally ``"scale:<param>"`` / ``"scale:<flow>"`` multipliers (see :attr:`Model.scale_keys`).
Flow names: ``"<link>.Q"`` (into the link's ``a``), ``"<radiation>.Q"`` (into ``a``), ``"<pe>.Q_hot"``,
``"<pe>.Q_cold"``, ``"<pe>.Q_internal"`` (conducted from the hot into the cold side), ``"<fluid>.Q"``
(into its node), ``"<source>.Q"``, ``"Q[<node>]"`` (a learned heat load).
"""

from __future__ import annotations

import graphlib
import math
import os
import types
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..core import Diagnostic, TnnError
from ..ir import POSITIVE_ROLES, Network
from . import learned as _learned
from . import physics as _physics
from .backends import get_xp
from .expressions import compile_expr, dependencies
from .integrators import INTEGRATORS, check_step, euler, expeuler, rk4

NOMINAL_T = 298.15
"""K: the temperature at which nominal quantities (time constants, default normalisation) are taken."""
T_SCALE = 10.0
"""K: default normalisation scale of temperatures fed to learned functions."""


@dataclass(frozen=True)
class ParamSpec:
    """One array of the model's parameter table.

    ``kind``: ``"physical"`` (a constant parameter, shape ``()``, SI), ``"weights"`` (a learned function's
    trainable array) or ``"stat"`` (a learned function's normalisation). ``trainable``: ``free``
    constants that are not learned targets, and weights of non-frozen functions. ``positive``: the
    parameter's role must stay positive (R, G, C, τ). ``lower``/``upper``: SI bounds of a ``free``
    parameter. ``role``: the parameter's role (``"generic"`` for learned arrays)."""

    name: str
    shape: tuple[int, ...]
    kind: str
    trainable: bool
    positive: bool
    lower: float | None
    upper: float | None
    role: str


def _err(msg: str, span=None, hint: str | None = None) -> TnnError:
    return TnnError([Diagnostic(msg, span, hint)])


# ---------------------------------------------------------------------------------------------
# The backend-independent plan
# ---------------------------------------------------------------------------------------------


class _Plan:
    """Everything about the network's structure that does not depend on the backend or the values."""

    def __init__(self, net: Network):
        self.net = net
        self.nodes = net.node_names
        self.n = len(self.nodes)
        self.node_idx = {name: i for i, name in enumerate(self.nodes)}
        self.bnds = net.boundary_names
        self.nb = len(self.bnds)
        self.bnd_idx = {name: j for j, name in enumerate(self.bnds)}
        self.bnd_param = {b.name: b.temperature for b in net.boundaries}
        self.params = {p.name: p for p in net.params}
        self.inputs = net.input_names
        self.input_idx = {name: i for i, name in enumerate(self.inputs)}
        self.lagged = [s for s in net.sensors if s.lag]
        self.state_names = tuple(self.nodes) + tuple(f"{s.name}.lag" for s in self.lagged)
        self.ns = len(self.state_names)
        self.fns = {fn.name: fn for fn in net.learned}

        if self.n == 0:
            raise _err(f"network {net.name!r} has no nodes", hint="declare at least one `node NAME C = ...`")
        for name in self.nodes:
            if name in self.bnd_idx:
                raise _err(f"{name!r} is both a node and a boundary")

        # learned targets
        self.param_targets: dict[str, tuple[Any, int]] = {}
        self.heat_loads: dict[str, tuple[Any, int]] = {}
        self.flow_targets: dict[str, tuple[Any, int]] = {}
        flow_names = {f"{pe.name}.Q_hot" for pe in net.peltiers} | {f"{pe.name}.Q_cold" for pe in net.peltiers}
        flow_names |= {f"{f.name}.Q" for f in net.fluids}
        for fn in net.learned:
            for i, t in enumerate(fn.targets):
                if t.kind == "param":
                    if t.name not in self.params:
                        raise _err(f"learned target {t.name!r} is not a parameter", t.span or fn.span)
                    self.param_targets[t.name] = (fn, i)
                elif t.kind == "heat_load":
                    if t.name not in self.node_idx:
                        raise _err(f"learned heat load Q[{t.name}] is not on a node", t.span or fn.span)
                    self.heat_loads[t.name] = (fn, i)
                else:
                    if t.name not in flow_names:
                        raise _err(
                            f"learned flow {t.name!r} is not a component flow", t.span or fn.span,
                            hint="flows that can be learned: " + ", ".join(sorted(flow_names)) if flow_names else None,
                        )
                    self.flow_targets[t.name] = (fn, i)

        # learn inputs resolved to ("node"|"boundary"|"input"|"param", name)
        self.fn_inputs: dict[str, list[tuple[str, str]]] = {}
        for fn in net.learned:
            res = []
            for inp in fn.inputs:
                res.append(self._resolve_learn_input(fn, inp))
            self.fn_inputs[fn.name] = res

        self._classify()
        self._flows()

    # -- name resolution -------------------------------------------------------------------------

    def _resolve_learn_input(self, fn, inp):
        name, kind = inp.name, inp.kind
        if kind in ("node", "unresolved") and name in self.node_idx:
            return ("node", name)
        if kind in ("node", "unresolved") and name in self.bnd_idx:
            return ("param", self.bnd_param[name])
        if kind in ("input", "unresolved") and name in self.input_idx:
            return ("input", name)
        if kind in ("param", "unresolved") and name in self.params:
            return ("param", name)
        raise _err(f"learned function {fn.name!r}: unknown input {name!r}", inp.span or fn.span)

    # -- static / dynamic classification -----------------------------------------------------------

    def _classify(self):
        deps: dict[tuple[str, str], set] = {}
        dyn_direct: set = set()
        node_direct: set = set()  # items that read a node temperature themselves
        for p in self.net.params:
            item = ("p", p.name)
            d = set()
            refs, temps = dependencies(p.expr)
            for r in refs:
                if r in self.params:
                    d.add(("p", r))
                elif r in self.input_idx:
                    dyn_direct.add(item)
                else:
                    raise _err(f"parameter {p.name!r} reads {r!r}, which is neither a parameter nor an input", p.span)
            for t in temps:
                if t in self.node_idx:
                    dyn_direct.add(item)
                    node_direct.add(item)
                elif t in self.bnd_idx:
                    d.add(("p", self.bnd_param[t]))
                else:
                    raise _err(f"parameter {p.name!r} reads T({t}), which is not a node or boundary", p.span)
            if p.name in self.param_targets:
                d.add(("f", self.param_targets[p.name][0].name))
            deps[item] = d
        for fn in self.net.learned:
            item = ("f", fn.name)
            d = set()
            for kind, name in self.fn_inputs[fn.name]:
                if kind in ("node", "input"):
                    dyn_direct.add(item)
                    if kind == "node":
                        node_direct.add(item)
                else:
                    d.add(("p", name))
            deps[item] = d
        try:
            order = list(graphlib.TopologicalSorter(deps).static_order())
        except graphlib.CycleError as e:
            cyc = " -> ".join(name for _, name in e.args[1])
            raise _err(f"circular definition: {cyc}",
                       hint="a parameter (or learned function) cannot depend on itself") from None
        static: dict = {}
        tdep: dict = {}  # depends (transitively) on a node temperature: evaluated every rhs call
        for item in order:
            static[item] = item not in dyn_direct and all(static[x] for x in deps[item])
            tdep[item] = item in node_direct or any(tdep[x] for x in deps[item])
        self.tdep = tdep
        self.deps = deps
        self.order = order
        self.static = static
        self.static_order = [it for it in order if static[it]]
        self.dyn_order = [it for it in order if not static[it]]

    def is_static(self, pname: str) -> bool:
        return self.static[("p", pname)]

    def ancestors(self, items) -> set:
        out: set = set()
        stack = list(items)
        while stack:
            it = stack.pop()
            if it in out:
                continue
            out.add(it)
            stack.extend(self.deps.get(it, ()))
        return out

    # -- element groups ------------------------------------------------------------------------------

    def _vertex(self, name, what, span):
        if name in self.node_idx:
            return ("n", self.node_idx[name])
        if name in self.bnd_idx:
            return ("b", self.bnd_idx[name])
        raise _err(f"{what}: {name!r} is not a node or boundary", span)

    def _flows(self):
        net = self.net
        # links: (flow key, a, b, param, form)
        links = [(f"{lk.name}.Q", lk.a, lk.b, lk.value, lk.form, lk.span) for lk in net.links]
        for pe in net.peltiers:
            if pe.r_internal:
                links.append((f"{pe.name}.Q_internal", pe.cold, pe.hot, pe.r_internal, "R", pe.span))
        self.links = [(k, self._vertex(a, k, s), self._vertex(b, k, s), p, form) for k, a, b, p, form, s in links]
        self.rads = [
            (f"{r.name}.Q", self._vertex(r.a, r.name, r.span), self._vertex(r.b, r.name, r.span),
             (r.area, r.emissivity, r.view_factor))
            for r in net.radiations
        ]
        self.peltiers = [
            (pe, self._vertex(pe.hot, pe.name, pe.span), self._vertex(pe.cold, pe.name, pe.span)) for pe in net.peltiers
        ]
        self.fluids = []
        for f in net.fluids:
            if f.node not in self.node_idx:
                raise _err(f"fluid {f.name!r} flows through {f.node!r}, which is not a node", f.span)
            self.fluids.append(f)
        for s in net.sources:
            if s.node not in self.node_idx:
                raise _err(f"source {s.name!r} heats {s.node!r}, which is not a node", s.span)
        for s in net.sensors:
            if s.node not in self.node_idx and s.node not in self.bnd_idx:
                raise _err(f"sensor {s.name!r} reads {s.node!r}, which is not a node or boundary", s.span)

        self.flow_keys = [k for k, *_ in self.links] + [k for k, *_ in self.rads]
        for pe in net.peltiers:
            self.flow_keys += [f"{pe.name}.Q_hot", f"{pe.name}.Q_cold"]
        self.flow_keys += [f"{f.name}.Q" for f in net.fluids] + [f"{s.name}.Q" for s in net.sources]
        self.flow_keys += [f"Q[{node}]" for node in self.heat_loads]
        self.scale_keys = tuple(f"scale:{p}" for p in self.params) + tuple(
            f"scale:{k}" for k in self.flow_keys if k not in self.params)

        # anchoring (for the steady state): every connected group of nodes needs a boundary or a fluid
        parent = list(range(self.n + 1))  # index n = "anchor"

        def find(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        def vid(v):
            return v[1] if v[0] == "n" else self.n

        for _, a, b, *_ in self.links + self.rads:
            parent[find(vid(a))] = find(vid(b))
        for pe, h, c in self.peltiers:
            parent[find(vid(h))] = find(vid(c))
        for f in self.fluids:
            parent[find(self.node_idx[f.node])] = find(self.n)
        self.unanchored = [self.nodes[i] for i in range(self.n) if find(i) != find(self.n)]


# ---------------------------------------------------------------------------------------------
# Per-call prepared values
# ---------------------------------------------------------------------------------------------


class _Prep:
    __slots__ = ("vals", "z", "arrays", "scales", "yscale", "fnlin", "M_nn", "M_bn", "Mr_nn", "Mr_bn", "cQ",
                 "Tb", "g_static_d", "invC", "inv_tau", "offsets", "diag_static", "diag_rad", "lin_fluid",
                 "tnom", "tscale", "L", "Lsl")


class _Env:
    __slots__ = ("vals", "z", "T", "u", "cx", "pre")

    def __init__(self, vals, z, T, u, cx=None, pre=None):
        self.vals = vals
        self.z = z
        self.T = T
        self.u = u
        self.cx = cx  # {fn: input-only part of the normalised input} when precomputed
        self.pre = pre  # {fn: first-layer pre-activation} for functions folded into the T-linear product


class _Core:
    """The plan bound to an array namespace: ``prepare(params)`` once per call, then ``rhs``,
    ``rhs_diag``, ``outputs``, ``heat_flows`` with the prepared values."""

    def __init__(self, plan: _Plan, xp):
        self.plan = plan
        self.xp = xp
        P = plan
        n, nb = P.n, P.nb

        # expression / item closures
        def ref(name):
            if name in P.params:
                return lambda env: env.vals[name]
            i = P.input_idx[name]
            return lambda env: env.u[..., i]

        def temp(node):
            if node in P.node_idx:
                i = P.node_idx[node]
                return lambda env: env.T[..., i]
            bp = P.bnd_param[node]
            return lambda env: env.vals[bp]

        # learned functions whose targets are all constant parameters of one positivity: their targets are
        # evaluated as one vector (a few array ops instead of a handful per target)
        self._vec_fns: dict[str, tuple[list[str], bool]] = {}
        for fn in P.net.learned:
            names = [t.name for t in fn.targets]
            if not names or any(t.kind != "param" for t in fn.targets) or len(set(names)) != len(names):
                continue
            if any(P.param_targets.get(nm, (None,))[0] is not fn for nm in names):
                continue
            if not all(P.params[nm].is_constant for nm in names):
                continue
            pos = {P.params[nm].role in POSITIVE_ROLES for nm in names}
            if len(pos) == 1:
                self._vec_fns[fn.name] = (names, pos.pop())
        self._vec_targets = {nm for names, _ in self._vec_fns.values() for nm in names}

        self._items = {}
        for p in P.net.params:
            if p.is_constant:  # the value comes from the parameter table, not from the IR literal
                expr_fn = (lambda name: lambda env: env.vals[name])(p.name)
            else:
                expr_fn = compile_expr(p.expr, xp, ref, temp)
            self._items[("p", p.name)] = self._param_item(p, expr_fn)
        for fn in P.net.learned:
            self._items[("f", fn.name)] = self._fn_item(fn)
        self._dyn_items = [self._items[it] for it in P.dyn_order]
        self._mono = {fn.name: _learned.monomial_index(len(fn.inputs), int(fn.degree or 2))
                      for fn in P.net.learned if fn.kind == "poly"}

        # which links / radiation / fluids are static
        self.links_s = [lk for lk in P.links if P.is_static(lk[3])]
        self.links_d = [lk for lk in P.links if not P.is_static(lk[3])]
        self.rads_s = [r for r in P.rads if all(P.is_static(q) for q in r[3])]
        self.rads_d = [r for r in P.rads if not all(P.is_static(q) for q in r[3])]
        self.fluids_lin = [f for f in P.fluids if f"{f.name}.Q" not in P.flow_targets
                           and all(P.is_static(q) for q in (f.mdot, f.cp, f.ua))]
        self.fluids_nl = [f for f in P.fluids if f not in self.fluids_lin]
        self.sources_s = [s for s in P.net.sources if P.is_static(s.value)]
        self.sources_d = [s for s in P.net.sources if not P.is_static(s.value)]
        self.bnd_static = all(P.is_static(P.bnd_param[b]) for b in P.bnds)
        self.C_static = all(P.is_static(nd.capacitance) for nd in P.net.nodes)
        self.tau_static = all(P.is_static(s.lag) for s in P.lagged)
        self.off_static = all(s.offset is None or P.is_static(s.offset) for s in P.net.sensors)

        asn = xp.asarray

        def incidence(group):
            D = np.zeros((n + nb, len(group)))
            Inc = np.zeros((len(group), n))
            for k, (_, a, b, *_r) in enumerate(group):
                ia = a[1] if a[0] == "n" else n + a[1]
                ib = b[1] if b[0] == "n" else n + b[1]
                D[ib, k] += 1.0
                D[ia, k] -= 1.0
                if a[0] == "n":
                    Inc[k, a[1]] += 1.0
                if b[0] == "n":
                    Inc[k, b[1]] -= 1.0
            return D, Inc

        self.D_ls, self.I_ls = incidence(self.links_s)  # numpy (used in prepare)
        D, Inc = incidence(self.links_d)
        self.Dd_n, self.Dd_b, self.Id = asn(D[:n]), asn(D[n:]), asn(Inc)
        self.Ad_neg = asn(-np.abs(Inc))
        self.D_rs, self.I_rs = incidence(self.rads_s)
        D, Inc = incidence(self.rads_d)
        self.Dr_n, self.Dr_b, self.Ir = asn(D[:n]), asn(D[n:]), asn(Inc)
        self.Ar_neg4 = asn(-4.0 * np.abs(Inc))
        self.has_links_s = bool(self.links_s) or bool(self.fluids_lin)

        # Input-only vs state-dependent work. Items that do not read a node temperature (directly or through
        # other items) depend on the inputs alone; ``rhs_u`` evaluates them once per sample (a rollout does it
        # for the whole input sequence at once, outside the time loop) together with every heat flow whose
        # coefficients are input-only, reduced to an affine form ``q + d·T`` per node. ``rhs_T`` then does only
        # the state-dependent work per right-hand-side evaluation.
        td = P.tdep
        self._u_items = [self._items[it] for it in P.dyn_order if not td[it]]
        self._t_items = [self._items[it] for it in P.dyn_order if td[it]]
        self._u_pnames = [nm for kd, nm in P.dyn_order if kd == "p" and not td[(kd, nm)]]
        self._u_fnames = [nm for kd, nm in P.dyn_order if kd == "f" and not td[(kd, nm)]]
        self._t_fnames = [nm for kd, nm in P.dyn_order if kd == "f" and td[(kd, nm)]]

        def tp(pname):  # parameter depends on a node temperature
            return td[("p", pname)]

        self.tb_u = not any(tp(P.bnd_param[b]) for b in P.bnds)  # boundary temperatures input-only
        ft = P.flow_targets
        self.pe_aff = [(pe, h, c) for pe, h, c in P.peltiers
                       if f"{pe.name}.Q_hot" not in ft and f"{pe.name}.Q_cold" not in ft
                       and not any(tp(q) for q in (pe.current, pe.seebeck, pe.resistance))
                       and (self.tb_u or (h[0] == "n" and c[0] == "n"))]
        self.pe_gen = [x for x in P.peltiers if x not in self.pe_aff]
        self.fnl_aff = [f for f in self.fluids_nl if f"{f.name}.Q" not in ft
                        and not any(tp(q) for q in (f.mdot, f.cp, f.ua, f.inlet))]
        self.fnl_gen = [f for f in self.fluids_nl if f not in self.fnl_aff]
        self.flin_u = [f for f in self.fluids_lin if not P.is_static(f.inlet) and not tp(f.inlet)]
        self.flin_t = [f for f in self.fluids_lin if not P.is_static(f.inlet) and tp(f.inlet)]
        self.src_u = [s for s in self.sources_d if not tp(s.value)]
        self.src_t = [s for s in self.sources_d if tp(s.value)]
        self.hl_u = [(node, fn, i) for node, (fn, i) in P.heat_loads.items()
                     if not P.static[("f", fn.name)] and not td[("f", fn.name)]]
        self.hl_t = [(node, fn, i) for node, (fn, i) in P.heat_loads.items() if td[("f", fn.name)]]

        def rows_matrix(rows):
            M = np.zeros((len(rows), n))
            for k, v in enumerate(rows):
                if v[0] == "n":
                    M[k, v[1]] = 1.0
            return asn(M)

        # input-only affine terms: rows of q (W) and of d (W/K) and their nodes
        qrows, drows = [], []
        for pe, h, c in self.pe_aff:
            qrows += [h, c]
            drows += [h, c]
        for f in self.fnl_aff:
            qrows.append(("n", P.node_idx[f.node]))
            drows.append(("n", P.node_idx[f.node]))
        qrows += [("n", P.node_idx[f.node]) for f in self.flin_u]
        qrows += [("n", P.node_idx[s.node]) for s in self.src_u]
        qrows += [("n", P.node_idx[node]) for node, _, _ in self.hl_u]
        self.Eq = rows_matrix(qrows) if qrows else None
        self.Ed = rows_matrix(drows) if drows else None
        self.has_ctx_q = bool(qrows) or (not self.bnd_static and self.tb_u and nb > 0
                                         and (bool(self.links_s) or bool(self.rads_s)))

        # point flows evaluated per rhs call (state-dependent): rows and their nodes
        rows = []
        for pe, h, c in self.pe_gen:
            rows.append(h)
            rows.append(c)
        rows += [("n", P.node_idx[f.node]) for f in self.fnl_gen]
        rows += [("n", P.node_idx[f.node]) for f in self.flin_t]
        rows += [("n", P.node_idx[s.node]) for s in self.src_t]
        rows += [("n", P.node_idx[node]) for node, _, _ in self.hl_t]
        self.n_point = len(rows)
        self.Pm = rows_matrix(rows)
        # diagonal terms (expeuler) of the state-dependent Peltier sides and non-linear fluids
        drows = []
        for pe, h, c in self.pe_gen:
            drows += [h, c]
        drows += [("n", P.node_idx[f.node]) for f in self.fnl_gen]
        self.Pd = rows_matrix(drows)
        # what rhs_T reads from the context: input-only parameters used by state-dependent work
        need = set()
        for it in P.dyn_order:
            if td[it]:
                need |= {nm for kd, nm in P.deps[it] if kd == "p"}
        need |= {lk[3] for lk in self.links_d}
        need |= {q for r in self.rads_d for q in r[3]}
        need |= {q for pe, _, _ in self.pe_gen for q in (pe.current, pe.seebeck, pe.resistance)}
        need |= {q for f in self.fnl_gen for q in (f.mdot, f.cp, f.ua, f.inlet)}
        if not self.C_static:
            need |= {nd.capacitance for nd in P.net.nodes}
        if not self.tau_static:
            need |= {s.lag for s in P.lagged}
        if not self.tb_u:
            need |= {P.bnd_param[b] for b in P.bnds}
        self._ctx_s = [nm for nm in self._u_pnames if nm in need]
        # links whose conductances are the targets of one vectorised, state-dependent learned function:
        # their conductance vector is a gather of the function's target vector
        self._links_vec = None
        self._links_d_keys = [lk[0] for lk in self.links_d]
        if self.links_d:
            ps = [lk[3] for lk in self.links_d]
            forms = {lk[4] for lk in self.links_d}
            owners = {P.param_targets[q][0].name if q in self._vec_targets else None for q in ps}
            if len(owners) == 1 and None not in owners and len(forms) == 1:
                fname = owners.pop()
                if td[("f", fname)]:
                    names = self._vec_fns[fname][0]
                    idx = [names.index(q) for q in ps]
                    self._links_vec = (fname, None if idx == list(range(len(names))) else idx, forms.pop())
        self._Tb_in_ctx = P.nb > 0 and self.tb_u and any(h[0] == "b" or c[0] == "b" for _, h, c in self.pe_gen)

        # lag states and outputs
        nl = len(P.lagged)
        Sl_n = np.zeros((n, nl))
        Sl_b = np.zeros((nb, nl))
        for k, s in enumerate(P.lagged):
            if s.node in P.node_idx:
                Sl_n[P.node_idx[s.node], k] = 1.0
            else:
                Sl_b[P.bnd_idx[s.node], k] = 1.0
        self.nl = nl
        self.Sl_n, self.Sl_b, self.lag_from_bnd = asn(Sl_n), asn(Sl_b), bool(Sl_b.any())
        Sy = np.zeros((P.ns, len(P.net.sensors)))
        Sy_b = np.zeros((nb, len(P.net.sensors)))
        lag_k = {s.name: k for k, s in enumerate(P.lagged)}
        for j, s in enumerate(P.net.sensors):
            if s.name in lag_k:
                Sy[n + lag_k[s.name], j] = 1.0
            elif s.node in P.node_idx:
                Sy[P.node_idx[s.node], j] = 1.0
            else:
                Sy_b[P.bnd_idx[s.node], j] = 1.0
        self.Sy, self.Sy_b, self.y_from_bnd = asn(Sy), asn(Sy_b), bool(Sy_b.any())
        need = set()
        if not self.off_static:
            need |= {("p", s.offset) for s in P.net.sensors if s.offset}
        if self.y_from_bnd and not self.bnd_static:
            need |= {("p", P.bnd_param[b]) for b in P.bnds}
        anc = P.ancestors(need)
        self._out_items = [self._items[it] for it in P.dyn_order if it in anc]

        # One T-linear product per right-hand side: every product of the node temperatures by a matrix that is
        # constant over a rollout — the static conductance matrix, the gather of dynamic links' endpoints, the
        # lag sources, and the first layer of state-dependent linear/MLP functions (their input gather and
        # normalisation folded into the weights, ``A_T·W0``; the input-only part ``cx·W0 + b0`` comes from
        # rhs_u, once per sample) — is one matmul ``Tn @ L`` by a matrix ``L`` assembled once per call in
        # ``prepare``, whose column blocks are sliced apart (on CPU each small product is a kernel launch).
        self._fold = []
        for fname in self._t_fnames:
            fn = P.fns[fname]
            ins = P.fn_inputs[fname]
            if fn.kind not in ("mlp", "linear") or not any(kd == "node" for kd, _ in ins):
                continue
            if any(kd == "param" and not P.is_static(nm) and td[("p", nm)] for kd, nm in ins):
                continue  # a state-dependent parameter input: the generic path
            self._fold.append(fname)
        blocks = []
        if self.has_links_s:
            blocks.append(("M", n))
        if self.links_d:
            blocks.append(("D", len(self.links_d)))
        if nl:
            blocks.append(("S", nl))
        for fname in self._fold:
            fn = P.fns[fname]
            width = int(fn.hidden[0]) if fn.kind == "mlp" and fn.hidden else len(fn.targets)
            blocks.append((f"f:{fname}", width))
        self._L_blocks = blocks

    # -- item closures ---------------------------------------------------------------------------

    def _param_item(self, p, expr_fn):
        xp = self.xp
        name = p.name
        target = self.plan.param_targets.get(name)
        positive = p.role in POSITIVE_ROLES
        if name in self._vec_targets:  # set by its function's item (vectorised)
            return _noop_item
        if target is None:
            def item(prep, env):
                v = expr_fn(env)
                s = prep.scales.get(name)
                env.vals[name] = v if s is None else v * s
            return item
        fn, i = target
        fname = fn.name

        def item_t(prep, env):
            v = expr_fn(env)
            v = _learned.target_value(xp, env.z[fname][..., i], v, positive, prep.yscale[fname][i])
            s = prep.scales.get(name)
            env.vals[name] = v if s is None else v * s
        return item_t

    def _fn_item(self, fn):
        xp = self.xp
        fname = fn.name

        def item(prep, env):
            pre = env.pre.get(fname) if env.pre is not None else None
            if pre is not None:  # first layer folded into rhs_T's one T-linear product (see _Core.__init__)
                z = _apply_from_first(xp, fn, prep.arrays[fname], pre)
            elif fname in prep.fnlin:  # dynamic: matmul gather + normalisation prepared once
                A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT = prep.fnlin[fname]
                cx = env.cx.get(fname) if env.cx is not None else None
                if cx is None:  # the input-only part
                    cx = self._fn_cx(prep, env, fname)
                xn = cx
                if A_T is not None:
                    xn = xn + xp.matmul(env.T, A_T)
                if dyn_pT:
                    xn = xn + xp.matmul(xp.stack([env.vals[q] for q in dyn_pT], axis=-1), A_pT)
                z = _learned.apply_normalised(xp, fn, prep.arrays[fname], xn, self._mono.get(fname))
            else:  # static: all inputs are static parameters
                arrays = prep.arrays[fname]
                ins = self.plan.fn_inputs[fname]
                if ins:
                    x = xp.stack([env.vals[q] for _, q in ins], axis=-1)
                    xn = _learned.normalise(x, arrays)
                else:
                    xn = None
                z = _learned.apply_normalised(xp, fn, prep.arrays[fname], xn, self._mono.get(fname))
            env.z[fname] = z
            if vec is not None:
                V = _learned.target_value(xp, z, prep.tnom[fname], positive, prep.arrays[fname]["y_scale"])
                sv = prep.tscale[fname]
                if sv is not None:
                    V = V * sv
                env.z[("V", fname)] = V
                for i, nm in enumerate(names):
                    env.vals[nm] = V[..., i]

        vec = self._vec_fns.get(fname)
        names, positive = vec if vec is not None else ((), False)
        return item

    def _fn_cx(self, prep, env, fname):
        """The input-only part of a dynamic function's normalised input: ``bias + u @ A_u + stack(input-only
        parameters) @ A_pu`` (``(..., n_in)``, or the bias alone)."""
        xp = self.xp
        A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT = prep.fnlin[fname]
        cx = bias
        if A_u is not None:
            cx = cx + xp.matmul(env.u, A_u)
        if dyn_pu:
            cx = cx + xp.matmul(xp.stack([env.vals[q] for q in dyn_pu], axis=-1), A_pu)
        return cx

    # -- prepare ---------------------------------------------------------------------------------

    def prepare(self, params) -> _Prep:
        xp, P = self.xp, self.plan
        n, nb = P.n, P.nb
        prep = _Prep()
        prep.scales = {k[6:]: xp.asarray(v) for k, v in params.items() if k.startswith("scale:")}
        prep.arrays = {}
        prep.yscale = {}
        for fn in P.net.learned:
            arrs = {k: xp.asarray(params[f"{fn.name}.{k}"]) for k in _learned.array_shapes(
                fn, len(fn.inputs), len(fn.targets))}
            prep.arrays[fn.name] = arrs
            prep.yscale[fn.name] = [arrs["y_scale"][i] for i in range(len(fn.targets))]
        vals = {p.name: xp.asarray(params[p.name]) for p in P.net.params if p.is_constant}
        prep.tnom, prep.tscale = {}, {}
        for fname, (names, _) in self._vec_fns.items():
            prep.tnom[fname] = xp.stack([vals[nm] for nm in names], axis=-1)
            if any(nm in prep.scales for nm in names):
                prep.tscale[fname] = xp.stack([prep.scales.get(nm, 1.0) for nm in names], axis=-1)
            else:
                prep.tscale[fname] = None
        env = _Env(vals, {}, None, None)
        prep.fnlin = {}
        for it in P.static_order:
            self._items[it](prep, env)
        prep.vals = env.vals
        prep.z = env.z
        for fn in P.net.learned:
            if not P.static[("f", fn.name)]:
                prep.fnlin[fn.name] = self._fnlin(fn, prep)
        sc = prep.scales

        def fscale(key, v):
            s = sc.get(key)
            return v if s is None else v * s

        # boundaries
        if nb and self.bnd_static:
            prep.Tb = xp.stack([vals[P.bnd_param[b]] for b in P.bnds], axis=-1) if nb else None
        else:
            prep.Tb = None
        cQ = None
        # static links (+ linear fluids on the diagonal)
        prep.M_nn = prep.M_bn = None
        if self.has_links_s:
            M = None
            if self.links_s:
                g = xp.stack([fscale(k, self._g(vals, p, form)) for k, _, _, p, form in self.links_s], axis=-1)
                M = _physics.conductance_matrix(xp, xp.asarray(self.D_ls), g, xp.asarray(self.I_ls))
            lin = []
            for f in self.fluids_lin:
                G = fscale(f"{f.name}.Q", _physics.fluid_conductance(xp, vals[f.mdot], vals[f.cp], vals[f.ua]))
                lin.append((f, G))
                E = np.zeros((n + nb, n))
                i = P.node_idx[f.node]
                E[i, i] = -1.0
                term = xp.asarray(E) * G
                M = term if M is None else M + term
                if P.is_static(f.inlet):
                    q = xp.asarray(np.eye(n)[i]) * (G * vals[f.inlet])
                    cQ = q if cQ is None else cQ + q
            prep.lin_fluid = lin
            prep.M_nn = M[:n]
            prep.M_bn = M[n:] if nb else None
            prep.diag_static = _diag(xp, prep.M_nn, n)
            if nb and self.bnd_static:
                q = xp.matmul(prep.Tb, prep.M_bn)
                cQ = q if cQ is None else cQ + q
                prep.M_bn = None
        else:
            prep.lin_fluid = []
            prep.diag_static = None
        # static radiation
        prep.Mr_nn = prep.Mr_bn = prep.diag_rad = None
        if self.rads_s:
            c = xp.stack([fscale(k, _physics.radiation_coefficient(vals[a], vals[e], vals[f]))
                          for k, _, _, (a, e, f) in self.rads_s], axis=-1)
            M = _physics.conductance_matrix(xp, xp.asarray(self.D_rs), c, xp.asarray(self.I_rs))
            prep.Mr_nn = M[:n]
            prep.diag_rad = 4.0 * _diag(xp, prep.Mr_nn, n)
            if nb:
                prep.Mr_bn = M[n:]
                if self.bnd_static:
                    q = xp.matmul(prep.Tb**4, prep.Mr_bn)
                    cQ = q if cQ is None else cQ + q
                    prep.Mr_bn = None
        # static sources and static learned heat loads
        for s in self.sources_s:
            q = xp.asarray(np.eye(n)[P.node_idx[s.node]]) * fscale(f"{s.name}.Q", vals[s.value])
            cQ = q if cQ is None else cQ + q
        for node, (fn, i) in P.heat_loads.items():
            if P.static[("f", fn.name)]:
                v = fscale(f"Q[{node}]", self._heat_load(prep, prep.z, fn, i))
                q = xp.asarray(np.eye(n)[P.node_idx[node]]) * v
                cQ = q if cQ is None else cQ + q
        prep.cQ = cQ
        if self.C_static:
            prep.invC = 1.0 / xp.stack([vals[nd.capacitance] for nd in P.net.nodes], axis=-1)
        else:
            prep.invC = None
        if self.nl and self.tau_static:
            prep.inv_tau = 1.0 / xp.stack([vals[s.lag] for s in P.lagged], axis=-1)
        else:
            prep.inv_tau = None
        if self.off_static and P.net.sensors:
            prep.offsets = xp.stack([vals[s.offset] if s.offset else 0.0 for s in P.net.sensors], axis=-1)
        else:
            prep.offsets = None
        prep.g_static_d = None
        prep.L, prep.Lsl = None, {}
        if self._L_blocks:
            parts, start = [], 0
            for key, width in self._L_blocks:
                if key == "M":
                    parts.append(prep.M_nn)
                elif key == "D":
                    parts.append(self.Dd_n)
                elif key == "S":
                    parts.append(self.Sl_n)
                else:
                    fname = key[2:]
                    W, _ = _first_layer(P.fns[fname], prep.arrays[fname])
                    parts.append(xp.matmul(prep.fnlin[fname][0][:n], W))
                prep.Lsl[key] = (start, start + width)
                start += width
            prep.L = parts[0] if len(parts) == 1 else xp.concat(parts, axis=-1)
        return prep

    def _fnlin(self, fn, prep):
        """Matrices that gather and normalise a dynamic function's inputs: ``xn = T @ A_T + u @ A_u +
        bias + stack(input-only params) @ A_pu + stack(state-dependent params) @ A_pT``."""
        xp, P = self.xp, self.plan
        arrs = prep.arrays[fn.name]
        ins = P.fn_inputs[fn.name]
        k = len(ins)
        inv = 1.0 / arrs["x_scale"]
        ST = np.zeros((P.ns, k))
        SU = np.zeros((len(P.inputs), k))
        static_vals: dict[int, str] = {}
        dyn_pu, dyn_pT = [], []
        SPu_rows, SPT_rows = [], []
        for j, (kind, name) in enumerate(ins):
            if kind == "node":
                ST[P.node_idx[name], j] = 1.0
            elif kind == "input":
                SU[P.input_idx[name], j] = 1.0
            elif P.is_static(name):
                static_vals[j] = name
            else:
                row = np.zeros(k)
                row[j] = 1.0
                if P.tdep[("p", name)]:
                    dyn_pT.append(name)
                    SPT_rows.append(row)
                else:
                    dyn_pu.append(name)
                    SPu_rows.append(row)
        bias = -arrs["x_mean"] * inv
        if static_vals:
            sv = [prep.vals[static_vals[j]] if j in static_vals else 0.0 for j in range(k)]
            bias = bias + xp.stack(sv, axis=-1) * inv
        A_T = xp.asarray(ST) * inv if ST.any() else None
        A_u = xp.asarray(SU) * inv if SU.any() else None
        A_pu = xp.asarray(np.asarray(SPu_rows)) * inv if dyn_pu else None
        A_pT = xp.asarray(np.asarray(SPT_rows)) * inv if dyn_pT else None
        return (A_T, A_u, bias, dyn_pu, A_pu, dyn_pT, A_pT)

    # -- shared helpers ----------------------------------------------------------------------------

    @staticmethod
    def _g(vals, p, form):
        return 1.0 / vals[p] if form == "R" else vals[p]

    def _heat_load(self, prep, z, fn, i):
        return _learned.target_value(self.xp, z[fn.name][..., i], 0.0, False, prep.yscale[fn.name][i], fn.replace)

    def _flow_target(self, prep, env, key, q):
        t = self.plan.flow_targets.get(key)
        if t is not None:
            fn, i = t
            q = _learned.target_value(self.xp, env.z[fn.name][..., i], q, False, prep.yscale[fn.name][i], fn.replace)
        s = prep.scales.get(key)
        return q if s is None else q * s

    @staticmethod
    def _vt(v, Tn, Tb):
        return Tn[..., v[1]] if v[0] == "n" else Tb[..., v[1]]

    def values(self, prep, T, u, items=None) -> _Env:
        env = _Env(dict(prep.vals), dict(prep.z), T, u)
        for item in (self._dyn_items if items is None else items):
            item(prep, env)
        return env

    def _Tb(self, prep, vals):
        P = self.plan
        if not P.nb:
            return None
        if prep.Tb is not None:
            return prep.Tb
        return self.xp.stack([vals[P.bnd_param[b]] for b in P.bnds], axis=-1)

    def _peltier(self, prep, env, pe, h, c, Tn, Tb):
        vals = env.vals
        I, S, R = vals[pe.current], vals[pe.seebeck], vals[pe.resistance]
        qh, qc = _physics.peltier_heat_flows(S, R, I, self._vt(h, Tn, Tb), self._vt(c, Tn, Tb))
        return (self._flow_target(prep, env, f"{pe.name}.Q_hot", qh),
                self._flow_target(prep, env, f"{pe.name}.Q_cold", qc), S * I)

    def _fluid_G(self, vals, f):
        return _physics.fluid_conductance(self.xp, vals[f.mdot], vals[f.cp], vals[f.ua])

    # -- the right-hand side ------------------------------------------------------------------------

    def rhs(self, prep, T, u, with_diag=False):
        """``dT/dt (..., n_states)`` K/s; with ``with_diag`` also the diagonal of the linear part (1/s)."""
        return self.rhs_T(prep, self.rhs_u(prep, u), T, with_diag)

    def rhs_u(self, prep, u) -> dict:
        """The input-only part of the right-hand side for inputs ``u (..., n_inputs)`` (any leading axes, e.g.
        a whole input sequence ``(..., N, n_inputs)``): a dict with ``"s"`` (input-only parameter values,
        shape ``u.shape[:-1]``), ``"v"`` (vectors ``(..., k)``: ``"q"`` heat (W) and ``"d"`` coefficients (W/K)
        of the affine node terms ``q + d·T``, ``"Tb"`` boundary temperatures and their products with the
        gather matrices, ``"cx:<fn>"`` input-only part of a learned function's normalised input,
        ``"z:<fn>"`` outputs of input-only learned functions) and ``"u"``. ``rhs_T`` reads one sample of it."""
        xp, P = self.xp, self.plan
        env = _Env(dict(prep.vals), dict(prep.z), None, u)
        for item in self._u_items:
            item(prep, env)
        vals = env.vals
        vec: dict = {}
        bshape = tuple(xp.shape(u)[:-1])

        def per_sample(v):  # every context array carries the samples' leading axes
            return xp.broadcast_to(v, (*bshape, *xp.shape(v)[-1:]))

        for fname in self._u_fnames:
            vec[f"z:{fname}"] = per_sample(env.z[fname])
        for fname in self._t_fnames:
            cx = self._fn_cx(prep, env, fname)
            if fname in self._fold:  # the input-only part of the first layer's pre-activation
                W, b = _first_layer(P.fns[fname], prep.arrays[fname])
                vec[f"cxw:{fname}"] = per_sample(xp.matmul(cx, W) + b)
            else:
                vec[f"cx:{fname}"] = per_sample(cx)
        Tb = None
        if P.nb and self.tb_u:
            Tb = self._Tb(prep, vals)
            if prep.Tb is None:  # input-dependent boundaries: broadcast to the samples
                Tb = xp.broadcast_to(Tb, (*bshape, P.nb))
                if self._Tb_in_ctx:
                    vec["Tb"] = Tb
                if self.links_d:
                    vec["tbD"] = xp.matmul(Tb, self.Dd_b)
                if self.rads_d:
                    vec["tbR"] = xp.matmul(Tb**4, self.Dr_b)
                if self.nl and self.lag_from_bnd:
                    vec["tbL"] = xp.matmul(Tb, self.Sl_b)
        q = None

        def add(a, b):
            return b if a is None else a + b

        if Tb is not None and prep.Tb is None:
            if prep.M_bn is not None:
                q = add(q, xp.matmul(Tb, prep.M_bn))
            if prep.Mr_bn is not None:
                q = add(q, xp.matmul(Tb**4, prep.Mr_bn))
        if self.Eq is not None:
            qs, ds = [], []
            for pe, h, c in self.pe_aff:
                I, S, R = vals[pe.current], vals[pe.seebeck], vals[pe.resistance]
                # Q_hot = S·T_hot·I + ½R I² (eq. 2.12–2.13) = d·T + q; a boundary side is a known temperature
                q_h, q_c = _physics.peltier_heat_flows(S, R, I, 0.0, 0.0)
                SI = S * I
                sh = prep.scales.get(f"{pe.name}.Q_hot")
                sc = prep.scales.get(f"{pe.name}.Q_cold")
                dh, dc = SI, -SI
                if h[0] == "b":
                    q_h = q_h + SI * Tb[..., h[1]]
                if c[0] == "b":
                    q_c = q_c - SI * Tb[..., c[1]]
                if sh is not None:
                    q_h, dh = q_h * sh, dh * sh
                if sc is not None:
                    q_c, dc = q_c * sc, dc * sc
                qs += [q_h, q_c]
                ds += [dh, dc]
            for f in self.fnl_aff:
                G = self._flow_scaled(prep, f"{f.name}.Q", self._fluid_G(vals, f))
                qs.append(G * vals[f.inlet])
                ds.append(-G)
            lin_G = {f.name: G for f, G in prep.lin_fluid}
            for f in self.flin_u:
                qs.append(lin_G[f.name] * vals[f.inlet])
            for s in self.src_u:
                qs.append(self._flow_scaled(prep, f"{s.name}.Q", vals[s.value]))
            for node, fn, i in self.hl_u:
                qs.append(self._flow_scaled(prep, f"Q[{node}]", self._heat_load(prep, env.z, fn, i)))
            q = add(q, xp.matmul(xp.broadcast_to(xp.stack(qs, axis=-1), (*bshape, len(qs))), self.Eq))
            if ds:
                vec["d"] = xp.matmul(xp.broadcast_to(xp.stack(ds, axis=-1), (*bshape, len(ds))), self.Ed)
        if q is not None:
            vec["q"] = per_sample(q if prep.cQ is None else q + prep.cQ)
        scal = {k: xp.broadcast_to(vals[k], bshape) for k in self._ctx_s}
        return {"s": scal, "v": vec, "u": u}

    def ctx_at(self, ctx, k):
        """Sample ``k`` of a sequence context from :meth:`rhs_u` (inputs ``(..., N, n_inputs)``)."""
        return {"s": {name: v[..., k] for name, v in ctx["s"].items()},
                "v": {name: v[..., k, :] for name, v in ctx["v"].items()},
                "u": ctx["u"][..., k, :]}

    def rhs_T(self, prep, ctx, T, with_diag=False):
        """The right-hand side from one sample's input-only context (:meth:`rhs_u`) and ``T (..., n_states)``."""
        xp, P = self.xp, self.plan
        n = P.n
        vec = ctx["v"]
        u = ctx["u"]
        vals = dict(prep.vals)
        vals.update(ctx["s"])
        z = dict(prep.z)
        cx = None
        if self._u_fnames or self._t_fnames:
            for fname in self._u_fnames:
                z[fname] = vec[f"z:{fname}"]
            cx = {fname: vec[f"cx:{fname}"] for fname in self._t_fnames if fname not in self._fold}
        Tn = T[..., :n] if self.nl else T
        TL = xp.matmul(Tn, prep.L) if prep.L is not None else None

        def block(key):
            a, b = prep.Lsl[key]
            return TL if (a, b) == (0, xp.shape(TL)[-1]) else TL[..., a:b]

        pre = {fname: vec[f"cxw:{fname}"] + block(f"f:{fname}") for fname in self._fold} if self._fold else None
        env = _Env(vals, z, T, u, cx, pre)
        for item in self._t_items:
            item(prep, env)
        dyn_b = not self.tb_u  # boundary terms not folded into the context
        Tb = vec.get("Tb")
        if Tb is None and P.nb and (dyn_b or prep.Tb is not None):
            Tb = self._Tb(prep, vals)
        dQ = vec.get("q", prep.cQ)
        diag = prep.diag_static if with_diag else None

        def add(a, b):
            return b if a is None else a + b

        if prep.M_nn is not None:
            dQ = add(dQ, block("M"))
            if dyn_b and prep.M_bn is not None:
                dQ = add(dQ, xp.matmul(Tb, prep.M_bn))
        d = vec.get("d")
        if d is not None:
            dQ = add(dQ, Tn * d)
            if with_diag:
                diag = add(diag, d)
        if prep.Mr_nn is not None:
            Tn3 = Tn * Tn * Tn
            dQ = add(dQ, xp.matmul(Tn3 * Tn, prep.Mr_nn))
            if dyn_b and prep.Mr_bn is not None:
                dQ = add(dQ, xp.matmul(Tb**4, prep.Mr_bn))
            if with_diag:
                diag = add(diag, Tn3 * prep.diag_rad)
        if self.links_d:
            lv = self._links_vec
            if lv is not None and not any(k in prep.scales for k in self._links_d_keys):
                V = env.z[("V", lv[0])]
                if lv[1] is not None:
                    V = V[..., lv[1]]
                g = 1.0 / V if lv[2] == "R" else V
            else:
                g = xp.stack([self._flow_scaled(prep, k, self._g(vals, p, form))
                              for k, _, _, p, form in self.links_d], axis=-1)
            dX = block("D")
            if P.nb:
                tbD = vec.get("tbD")
                dX = dX + (tbD if tbD is not None else xp.matmul(Tb, self.Dd_b))
            dQ = add(dQ, xp.matmul(g * dX, self.Id))
            if with_diag:
                diag = add(diag, xp.matmul(g, self.Ad_neg))
        if self.rads_d:
            c = xp.stack([self._flow_scaled(prep, k, _physics.radiation_coefficient(vals[a], vals[e], vals[f]))
                          for k, _, _, (a, e, f) in self.rads_d], axis=-1)
            dX = xp.matmul(Tn**4, self.Dr_n)
            if P.nb:
                tbR = vec.get("tbR")
                dX = dX + (tbR if tbR is not None else xp.matmul(Tb**4, self.Dr_b))
            dQ = add(dQ, xp.matmul(c * dX, self.Ir))
            if with_diag:
                diag = add(diag, Tn**3 * xp.matmul(c, self.Ar_neg4))
        if self.n_point:
            pts = []
            dterms = []
            for pe, h, c in self.pe_gen:
                qh, qc, SI = self._peltier(prep, env, pe, h, c, Tn, Tb)
                pts += [qh, qc]
                if with_diag:
                    dterms += [self._diag_term(prep, f"{pe.name}.Q_hot", SI),
                               self._diag_term(prep, f"{pe.name}.Q_cold", -SI)]
            for f in self.fnl_gen:
                G = self._fluid_G(vals, f)
                q = G * (vals[f.inlet] - Tn[..., P.node_idx[f.node]])
                pts.append(self._flow_target(prep, env, f"{f.name}.Q", q))
                if with_diag:
                    dterms.append(self._diag_term(prep, f"{f.name}.Q", -G))
            if self.flin_t:
                lin_G = {f.name: G for f, G in prep.lin_fluid}
                for f in self.flin_t:
                    pts.append(lin_G[f.name] * vals[f.inlet])
            for s in self.src_t:
                pts.append(self._flow_scaled(prep, f"{s.name}.Q", vals[s.value]))
            for node, fn, i in self.hl_t:
                pts.append(self._flow_scaled(prep, f"Q[{node}]", self._heat_load(prep, env.z, fn, i)))
            dQ = add(dQ, xp.matmul(xp.stack(pts, axis=-1), self.Pm))
            if with_diag and dterms:
                diag = add(diag, xp.matmul(xp.stack(dterms, axis=-1), self.Pd))
        if dQ is None:
            dQ = Tn * 0.0
        invC = prep.invC if prep.invC is not None else 1.0 / xp.stack(
            [vals[nd.capacitance] for nd in P.net.nodes], axis=-1)
        dT = dQ * invC
        if with_diag:
            diag = (Tn * 0.0 if diag is None else diag) * invC
        if self.nl:
            inv_tau = prep.inv_tau if prep.inv_tau is not None else 1.0 / xp.stack(
                [vals[s.lag] for s in P.lagged], axis=-1)
            src = block("S")
            if self.lag_from_bnd:
                tbL = vec.get("tbL")
                src = src + (tbL if tbL is not None else xp.matmul(Tb, self.Sl_b))
            dTl = (src - T[..., n:]) * inv_tau
            dT = xp.concat([xp.broadcast_to(dT, (*xp.shape(dTl)[:-1], n)), dTl], axis=-1)
            if with_diag:
                diag = xp.concat([xp.broadcast_to(diag, xp.shape(dT[..., :n])),
                                  xp.broadcast_to(-inv_tau, xp.shape(dTl))], axis=-1)
        return (dT, diag) if with_diag else dT

    def _flow_scaled(self, prep, key, q):
        s = prep.scales.get(key)
        return q if s is None else q * s

    def _diag_term(self, prep, key, d):
        t = self.plan.flow_targets.get(key)
        if t is not None and t[0].replace:
            return d * 0.0
        return self._flow_scaled(prep, key, d)

    # -- outputs and flows ------------------------------------------------------------------------

    def outputs(self, prep, T, u):
        """Sensor readings ``(..., n_outputs)`` K for states ``T (..., n_states)``."""
        xp, P = self.xp, self.plan
        if not P.net.sensors:
            return T[..., :0]
        y = xp.matmul(T, self.Sy)
        vals = None
        if self._out_items or self.y_from_bnd:
            vals = self.values(prep, T, u, self._out_items).vals
        if self.y_from_bnd:
            y = y + xp.matmul(self._Tb(prep, vals), self.Sy_b)
        off = prep.offsets if prep.offsets is not None else xp.stack(
            [vals[s.offset] if s.offset else 0.0 for s in P.net.sensors], axis=-1)
        return y + off

    def heat_flows(self, prep, T, u) -> dict:
        """Every flow (W) by name, element by element (for inspection; see the module docstring)."""
        xp, P = self.xp, self.plan
        env = self.values(prep, T, u)
        vals = env.vals
        Tn = T[..., : P.n]
        Tb = self._Tb(prep, vals)
        out = {}
        for k, a, b, p, form in P.links:
            g = self._flow_scaled(prep, k, self._g(vals, p, form))
            out[k] = _physics.link_heat_flow(g, self._vt(a, Tn, Tb), self._vt(b, Tn, Tb))
        for k, a, b, (ar, e, f) in P.rads:
            q = _physics.radiation_heat_flow(vals[ar], vals[e], vals[f], self._vt(a, Tn, Tb), self._vt(b, Tn, Tb))
            out[k] = self._flow_scaled(prep, k, q)
        for pe, h, c in P.peltiers:
            qh, qc, _ = self._peltier(prep, env, pe, h, c, Tn, Tb)
            out[f"{pe.name}.Q_hot"], out[f"{pe.name}.Q_cold"] = qh, qc
        for f in P.fluids:
            q = _physics.fluid_heat_flow(xp, vals[f.mdot], vals[f.cp], vals[f.ua], vals[f.inlet],
                                         Tn[..., P.node_idx[f.node]])
            out[f"{f.name}.Q"] = self._flow_target(prep, env, f"{f.name}.Q", q)
        for s in P.net.sources:
            out[f"{s.name}.Q"] = self._flow_scaled(prep, f"{s.name}.Q", vals[s.value])
        for node, (fn, i) in P.heat_loads.items():
            out[f"Q[{node}]"] = self._flow_scaled(prep, f"Q[{node}]", self._heat_load(prep, env.z, fn, i))
        shape = xp.shape(Tn)[:-1]
        return {k: xp.broadcast_to(xp.asarray(v) if isinstance(v, float) else v, shape) for k, v in out.items()}


def _noop_item(prep, env):
    return None


def _first_layer(fn, arrays):
    """``(W, b)`` of the first (linear) layer of a ``linear`` or ``mlp`` learned function."""
    return (arrays["W"], arrays["b"]) if fn.kind == "linear" else (arrays["W0"], arrays["b0"])


def _apply_from_first(xp, fn, arrays, pre):
    """The raw output ``z`` of a ``linear``/``mlp`` function from its first layer's pre-activation
    ``pre = xn @ W0 + b0`` (the rest of :func:`tnn_dsl.compiler.learned.apply_normalised`)."""
    if fn.kind == "linear":
        return pre
    act = _learned.activation(xp, fn.activation)
    n_layers = len(fn.hidden) + 1
    h = pre
    for k in range(1, n_layers):
        h = xp.matmul(act(h), arrays[f"W{k}"]) + arrays[f"b{k}"]
    return h


def _diag(xp, M, n):
    idx = np.arange(n)
    return M[idx, idx] if xp.name != "torch" else M.diagonal()


# ---------------------------------------------------------------------------------------------
# The model
# ---------------------------------------------------------------------------------------------


class TorchCompileWarning(UserWarning):
    """``torch.compile`` was asked for but failed; the torch model runs eager."""


class Model:
    """A compiled network (see docs/architecture.md, "The compiled model"). Build with :func:`compile`.

    Shapes: ``T (..., n_states)`` K, ``u (..., n_inputs)`` SI (temperature inputs in K), outputs
    ``(..., n_outputs)`` K. Leading axes broadcast (batches of windows)."""

    def __init__(self, net: Network, backend: str = "jax", dtype: str = "float64", torch_compile: bool = False):
        if not isinstance(net, Network):
            raise TypeError(f"compile() needs a tnn_dsl.Network, got {type(net).__name__}")
        self.network = net
        self.backend = backend
        self.dtype = dtype
        self.torch_compile = bool(torch_compile) and backend == "torch"
        """Whether torch rollouts run each integration step through ``torch.compile`` (see :func:`compile`)."""
        self.xp = get_xp(backend, dtype)
        self._plan = _Plan(net)
        self._core = _Core(self._plan, self.xp)
        P = self._plan
        self.state_names = P.state_names
        self.input_names = tuple(P.inputs)
        self.output_names = tuple(s.name for s in net.sensors)
        self.scale_keys = P.scale_keys
        self.flow_names = tuple(P.flow_keys)
        self.param_specs = self._specs()
        self._jit_cache: dict = {}
        self._nominal_np = None
        self._tau = None

    # -- parameters ------------------------------------------------------------------------------

    def _specs(self) -> dict[str, ParamSpec]:
        P = self._plan
        specs: dict[str, ParamSpec] = {}
        for p in self.network.params:
            if p.is_constant:
                specs[p.name] = ParamSpec(
                    p.name, (), "physical", bool(p.free) and p.name not in P.param_targets,
                    p.role in POSITIVE_ROLES, p.lower, p.upper, p.role)
        for fn in self.network.learned:
            for k, (shape, kind) in _learned.array_shapes(fn, len(fn.inputs), len(fn.targets)).items():
                name = f"{fn.name}.{k}"
                specs[name] = ParamSpec(name, shape, kind, kind == "weights" and not fn.frozen, False, None, None,
                                        "generic")
        return specs

    def _init_numpy(self, seed: int = 0) -> dict[str, np.ndarray]:
        P = self._plan
        rng = np.random.default_rng(seed)
        out: dict[str, np.ndarray] = {p.name: np.asarray(float(p.value)) for p in self.network.params if p.is_constant}
        for fn in self.network.learned:
            arrs = _learned.init_arrays(fn, len(fn.inputs), len(fn.targets), rng)
            out.update({f"{fn.name}.{k}": v for k, v in arrs.items()})
        # default normalisation from nominal values (targets equal their nominal at z = 0)
        nominal = self._nominal_values(out)
        for fn in self.network.learned:
            xm, xs = [], []
            for kind, name in P.fn_inputs[fn.name]:
                if kind == "node" or (kind == "input" and self.network.inputs[P.input_idx[name]].is_temperature):
                    xm.append(NOMINAL_T)
                    xs.append(T_SCALE)
                elif kind == "input":
                    xm.append(0.0)
                    xs.append(1.0)
                else:
                    v = float(np.mean(nominal.get(name, 0.0)))
                    xm.append(v)
                    xs.append(abs(v) if v != 0 and math.isfinite(v) else 1.0)
            ys = []
            for t in fn.targets:
                if t.kind == "param":
                    v = float(np.mean(nominal.get(t.name, 1.0)))
                    ys.append(abs(v) if v != 0 and math.isfinite(v) else 1.0)
                else:
                    ys.append(1.0)
            out[f"{fn.name}.x_mean"] = np.asarray(xm, dtype=float).reshape(len(fn.inputs))
            out[f"{fn.name}.x_scale"] = np.asarray(xs, dtype=float).reshape(len(fn.inputs))
            out[f"{fn.name}.y_scale"] = np.asarray(ys, dtype=float)
        return out

    def _nominal_values(self, params_np) -> dict[str, Any]:
        """Parameter values at the nominal point (T = 298.15 K, inputs 0 or 298.15 K) with numpy."""
        core = _Core(self._plan, get_xp("numpy")) if self.backend != "numpy" else self._core
        prep = core.prepare(params_np)
        T = np.full(self._plan.ns, NOMINAL_T)
        env = core.values(prep, T, self._nominal_u())
        return {k: np.asarray(v) for k, v in env.vals.items()}

    def _nominal_u(self):
        return np.asarray([NOMINAL_T if i.is_temperature else 0.0 for i in self.network.inputs], dtype=float)

    def init_params(self, seed: int = 0) -> dict:
        """The parameter table: constants at their SI values, learned arrays initialised (``seed``)."""
        return self.from_numpy(self._init_numpy(seed))

    def to_numpy(self, params) -> dict[str, np.ndarray]:
        """Backend arrays → float64 numpy arrays (copies)."""
        return {k: np.array(self.xp.to_numpy(v), dtype=np.float64) for k, v in params.items()}

    def from_numpy(self, arrays) -> dict:
        """numpy arrays (or floats) → backend arrays in the model's dtype."""
        out = {}
        for k, v in arrays.items():
            a = np.asarray(v, dtype=np.float64)
            spec = self.param_specs.get(k)
            if spec is not None and tuple(a.shape) != tuple(spec.shape):
                raise TnnError(f"parameter {k!r} has shape {a.shape}, the model expects {spec.shape}")
            out[k] = self.xp.asarray(a)
        return out

    def _check(self, params):
        missing = [k for k in self.param_specs if k not in params]
        if missing:
            raise TnnError(
                [Diagnostic(f"the parameter table lacks {', '.join(repr(m) for m in missing[:8])}"
                            + (f" and {len(missing) - 8} more" if len(missing) > 8 else ""),
                            hint="start from model.init_params() and change values in place")])
        bad = [k for k in params if k.startswith("scale:") and k not in self._scale_set]
        if bad:
            raise TnnError([Diagnostic(f"unknown scale key {bad[0]!r}",
                                       hint="scale keys are 'scale:<parameter>' or 'scale:<flow>'; see model.scale_keys")])

    @property
    def _scale_set(self):
        s = getattr(self, "_scale_set_cache", None)
        if s is None:
            s = self._scale_set_cache = set(self.scale_keys)
        return s

    def _prepare(self, params):
        self._check(params)
        return self._core.prepare(params)

    # -- time constants --------------------------------------------------------------------------

    def time_constants(self, params=None) -> dict[str, float]:
        """``{state: τ}`` (s) = ``−1/d`` from the diagonal of the linear part at the nominal point
        (default parameters unless given as numpy-convertible ``params``); ``inf`` where d ≥ 0."""
        p_np = self._init_numpy(0) if params is None else self.to_numpy(params)
        core = _Core(self._plan, get_xp("numpy"))
        prep = core.prepare(p_np)
        T = np.full(self._plan.ns, NOMINAL_T)
        _, d = core.rhs(prep, T, self._nominal_u(), with_diag=True)
        d = np.broadcast_to(np.asarray(d, dtype=float), (self._plan.ns,))
        return {name: (-1.0 / di if di < 0 else math.inf) for name, di in zip(self.state_names, d)}

    def fastest_time_constant(self) -> tuple[float, str]:
        """``(τ_min (s), state name)`` at nominal parameters (cached)."""
        if self._tau is None:
            tc = self.time_constants()
            name = min(tc, key=tc.get)
            self._tau = (tc[name], name)
        return self._tau

    # -- evaluation ------------------------------------------------------------------------------

    def _arr(self, x):
        return self.xp.asarray(x)

    def rhs(self, params, T, u):
        """``dT/dt (..., n_states)`` K/s for ``T (..., n_states)`` K and ``u (..., n_inputs)`` SI."""
        if self.backend == "jax":
            return self._jitted("rhs")(params, self._arr(T), self._arr(u))
        return self._core.rhs(self._prepare(params), self._arr(T), self._arr(u))

    def outputs(self, params, T, u):
        """Sensor readings ``(..., n_outputs)`` K (node or lag state + offset)."""
        if self.backend == "jax":
            return self._jitted("outputs")(params, self._arr(T), self._arr(u))
        return self._core.outputs(self._prepare(params), self._arr(T), self._arr(u))

    def heat_flows(self, params, T, u) -> dict:
        """Every link/component flow (W) by name (see :attr:`flow_names`), shape ``T.shape[:-1]``."""
        if self.backend == "jax":
            return self._jitted("heat_flows")(params, self._arr(T), self._arr(u))
        return self._core.heat_flows(self._prepare(params), self._arr(T), self._arr(u))

    def rhs_and_diag(self, params, T, u):
        """``(dT/dt, d)``: the right-hand side and the diagonal of its linear part (1/s), as used by
        ``expeuler``."""
        return self._core.rhs(self._prepare(params), self._arr(T), self._arr(u), with_diag=True)

    def _jitted(self, what, *static):
        key = (what, *static)
        f = self._jit_cache.get(key)
        if f is None:
            import jax

            core = self._core
            if what == "rollout":
                dt, integrator, substeps = static
                f = jax.jit(lambda p, T0, U: self._rollout_impl(p, T0, U, dt, integrator, substeps))
            elif what == "steady":
                max_iter, tol = static
                f = jax.jit(lambda p, u, T0: self._steady_impl(p, u, T0, max_iter, tol))
            else:
                method = getattr(core, what)
                f = jax.jit(lambda p, T, u: method(self._prepare(p), T, u))
            self._jit_cache[key] = f
        return f

    # -- rollout -------------------------------------------------------------------------------------

    def rollout(self, params, T0, inputs, dt, integrator: str = "rk4", substeps: int | None = None):
        """Simulate from ``T0 (..., n_states)`` K with ``inputs (..., N, n_inputs)`` held over each interval
        of ``dt`` seconds. Returns ``(states (..., N, n_states), outputs (..., N, n_outputs))`` with
        ``states[..., 0, :] = T0`` and ``outputs[..., k, :]`` the sensors at ``states[k]``, ``inputs[k]``.

        ``integrator``: ``"euler"`` (eq. 4.7), ``"rk4"`` or ``"expeuler"`` (stiff-stable). With
        ``substeps=None`` explicit methods sub-step automatically (and warn) when ``dt`` exceeds their
        stability limit for the network's fastest time constant at nominal parameters."""
        if integrator not in INTEGRATORS:
            raise TnnError([Diagnostic(f"unknown integrator {integrator!r}",
                                       hint="use one of: " + ", ".join(INTEGRATORS))])
        tau, where = self.fastest_time_constant()
        dt = float(dt)
        sub = check_step(integrator, dt, tau, substeps, where)
        T0 = self._arr(T0)
        inputs = self._arr(inputs)
        ns, ni = len(self.state_names), len(self.input_names)
        if self.xp.shape(T0)[-1:] != (ns,):
            raise TnnError(f"T0 must have shape (..., {ns}) (states: {', '.join(self.state_names)}), "
                           f"got {self.xp.shape(T0)}")
        if len(self.xp.shape(inputs)) < 2 or self.xp.shape(inputs)[-1] != ni:
            raise TnnError(f"inputs must have shape (..., N, {ni}) (inputs: {', '.join(self.input_names)}), "
                           f"got {self.xp.shape(inputs)}")
        if self.backend == "jax":
            self._check(params)
            return self._jitted("rollout", dt, integrator, sub)(params, T0, inputs)
        return self._rollout_impl(params, T0, inputs, dt, integrator, sub)

    def _stepper(self, prep, dt, integrator, sub):
        """``step(T, ctx) -> T_next`` over one sample interval; ``ctx`` is one sample of
        :meth:`_Core.rhs_u` (the input-only work is done once per sample, not per stage)."""
        core, xp = self._core, self.xp
        h = dt / sub
        if integrator == "expeuler":
            def one(T, c):
                return expeuler(lambda x: core.rhs_T(prep, c, x, with_diag=True), T, h, xp)
        else:
            method = euler if integrator == "euler" else rk4

            def one(T, c):
                return method(lambda x: core.rhs_T(prep, c, x), T, h)
        if sub == 1:
            return one
        if self.backend == "jax" and sub > 4:
            import jax

            def many(T, c):
                return jax.lax.fori_loop(0, sub, lambda i, x: one(x, c), T)
            return many

        def many_py(T, c):
            for _ in range(sub):
                T = one(T, c)
            return T
        return many_py

    def _compiled_torch_step(self, prep, dt, integrator, sub):
        """``step(T, ctx)`` as in :meth:`_stepper`, run through ``torch.compile`` (one graph per sample
        interval, ``prep`` an input so that new parameters reuse it). The compiled function is kept per
        ``(dt, integrator, sub)``; torch recompiles it for new shapes (dynamic after the second). If torch
        cannot compile here (inductor needs a C++ compiler), the model warns once and runs eager."""
        import torch

        key = ("torch_step", dt, integrator, sub)
        compiled = self._jit_cache.get(key)
        if compiled is None:
            def full_step(prep, T, c):
                return self._stepper(prep, dt, integrator, sub)(T, c)
            # torch keeps compiled code per code object, with a limit on variants: a code object of this
            # model's own keeps models apart (and one model's shapes from exhausting another's limit)
            code = full_step.__code__.replace(co_name=f"tnn_step_{id(self):x}_{len(self._jit_cache)}")
            full_step = types.FunctionType(code, full_step.__globals__, code.co_name, None, full_step.__closure__)
            compiled = torch.compile(full_step, fullgraph=True)
            self._jit_cache[key] = compiled
        eager = self._stepper(prep, dt, integrator, sub)

        def step(T, c):
            if self.torch_compile:
                try:
                    return compiled(prep, T, c)
                except Exception as e:  # noqa: BLE001 - compiler infrastructure, not the user's model
                    self.torch_compile = False
                    warnings.warn(f"torch.compile failed ({type(e).__name__}: {str(e)[:200]}); the model runs "
                                  "eager from here on", TorchCompileWarning, stacklevel=4)
            return eager(T, c)
        return step

    def _rollout_impl(self, params, T0, inputs, dt, integrator, sub):
        xp = self.xp
        prep = self._prepare(params)
        if self.torch_compile:
            step = self._compiled_torch_step(prep, dt, integrator, sub)
        else:
            step = self._stepper(prep, dt, integrator, sub)
        N = xp.shape(inputs)[-2]
        batch = np.broadcast_shapes(xp.shape(T0)[:-1], xp.shape(inputs)[:-2])
        T0 = xp.broadcast_to(T0, (*batch, xp.shape(T0)[-1]))
        # the input-only part of the right-hand side, for every sample at once (outside the time loop)
        ctx = self._core.rhs_u(prep, inputs[..., : max(N - 1, 0), :]) if N > 1 else None
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            # Reverse mode recomputes each sample's step from its start state instead of storing every stage's
            # intermediates (one store per intermediate per step): forward+gradient / forward 3.1 instead of 5.4
            # batched, 3.9 instead of 6.3 single (benchmarks/bench_rollout.py, case study M3).
            step = jax.checkpoint(step)

            def body(T, c):
                Tn = step(T, c)
                return Tn, Tn

            if N > 1:
                xs = {"s": {k: jnp.moveaxis(v, -1, 0) for k, v in ctx["s"].items()},
                      "v": {k: jnp.moveaxis(v, -2, 0) for k, v in ctx["v"].items()},
                      "u": jnp.moveaxis(ctx["u"], -2, 0)}
                _, rest = jax.lax.scan(body, T0, xs)
                states = jnp.concatenate([T0[None], rest], axis=0)
            else:
                states = T0[None][:N]
            states = jnp.moveaxis(states, 0, -2)
        else:
            T = T0
            states = [T]
            if N > 1:
                if self.backend == "numpy":
                    def split(v, ax):
                        return [np.take(v, k, axis=ax) for k in range(N - 1)]
                elif self.torch_compile:
                    def split(v, ax):  # contiguous samples: the compiled step is specialised on strides
                        return xp.moveaxis(v, ax, 0).contiguous().unbind(0)
                else:
                    def split(v, ax):
                        return v.unbind(ax)
                s_l = {k: split(v, -1) for k, v in ctx["s"].items()}
                v_l = {k: split(v, -2) for k, v in ctx["v"].items()}
                u_l = split(ctx["u"], -2)
                for k in range(N - 1):
                    c = {"s": {name: a[k] for name, a in s_l.items()},
                         "v": {name: a[k] for name, a in v_l.items()}, "u": u_l[k]}
                    T = step(T, c)
                    states.append(T)
            states = xp.stack(states[:N], axis=-2) if N > 0 else xp.zeros((*batch, 0, xp.shape(T0)[-1]))
        outputs = self._core.outputs(prep, states, inputs)
        return states, outputs

    # -- steady state --------------------------------------------------------------------------------

    def steady_state(self, params, u, T_init=None, max_iter: int = 50, tol: float = 1e-10):
        """The steady state ``T* (..., n_states)`` K with ``f(T*, u) = 0`` for constant inputs
        ``u (..., n_inputs)`` (thesis eq. 4.1).

        Newton's method from ``T_init`` (default 298.15 K everywhere; its first step is the linear solve),
        at most ``max_iter`` iterations, stopping at a step below ``tol`` K. Differentiable: the iteration
        runs without gradient and one final Newton step with the Jacobian held fixed carries the
        implicit-function derivative ``dT*/dθ = −J⁻¹ ∂f/∂θ``."""
        P = self._plan
        if P.unanchored:
            raise TnnError([Diagnostic(
                f"no steady state: node(s) {', '.join(P.unanchored)} have no path to a boundary or fluid, so "
                "their temperature at rest depends on the initial state",
                hint="connect them to a boundary, or simulate with rollout() instead")])
        u = self._arr(u)
        T_init = None if T_init is None else self._arr(T_init)
        if self.backend == "jax":
            self._check(params)
            if T_init is None:
                T_init = self.xp.asarray(np.full(P.ns, NOMINAL_T))
            return self._jitted("steady", max_iter, tol)(params, u, T_init)
        return self._steady_impl(params, u, T_init, max_iter, tol)

    def _jac(self, prep, T, u):
        """Jacobian ``∂f/∂T (..., n, n)`` (no gradient w.r.t. parameters)."""
        core = self._core
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            J = jnp.vectorize(jax.jacfwd(lambda x, v: core.rhs(prep, x, v)), signature="(n),(m)->(n,n)")(T, u)
            return J
        if self.backend == "torch":
            import torch

            batch = T.shape[:-1]
            n = T.shape[-1]
            Tf = T.reshape(-1, n)
            uf = torch.broadcast_to(u, (*batch, u.shape[-1])).reshape(Tf.shape[0], u.shape[-1])
            J = torch.func.vmap(torch.func.jacfwd(lambda x, v: core.rhs(prep, x, v)))(Tf, uf)
            return J.reshape(*batch, n, n)
        # numpy: central differences (reference backend only)
        n = T.shape[-1]
        cols = []
        for j in range(n):
            e = np.zeros(n)
            e[j] = 1e-4
            cols.append((core.rhs(prep, T + e, u) - core.rhs(prep, T - e, u)) / 2e-4)
        return np.stack(cols, axis=-1)

    def _steady_impl(self, params, u, T_init=None, max_iter=50, tol=1e-10):
        xp, core, P = self.xp, self._core, self._plan
        prep = self._prepare(params)
        batch = tuple(xp.shape(u)[:-1])
        if T_init is None:
            T_init = xp.asarray(np.full(P.ns, NOMINAL_T))
        T = xp.broadcast_to(T_init, (*batch, P.ns)) * 1.0
        if self.backend == "jax":
            import jax
            import jax.numpy as jnp

            prep0 = self._core.prepare({k: jax.lax.stop_gradient(v) for k, v in params.items()})
            u0 = jax.lax.stop_gradient(u)

            def cond(c):
                k, _, delta = c
                return (k < max_iter) & (delta > tol)

            def body(c):
                k, x, _ = c
                J = self._jac(prep0, x, u0)
                dx = jnp.linalg.solve(J, core.rhs(prep0, x, u0)[..., None])[..., 0]
                return k + 1, x - dx, jnp.max(jnp.abs(dx))

            _, Ts, _ = jax.lax.while_loop(cond, body, (0, jax.lax.stop_gradient(T), jnp.asarray(jnp.inf, T.dtype)))
            Ts = jax.lax.stop_gradient(Ts)
            J = jax.lax.stop_gradient(self._jac(prep0, Ts, u0))
            return Ts - xp.solve(J, core.rhs(prep, Ts, u))
        if self.backend == "torch":
            import torch

            with torch.no_grad():
                prep0 = self._core.prepare({k: v.detach() if hasattr(v, "detach") else v for k, v in params.items()})
                x = T.detach().clone()
                u0 = u.detach()
                for _ in range(max_iter):
                    J = self._jac(prep0, x, u0)
                    dx = xp.solve(J, core.rhs(prep0, x, u0))
                    x = x - dx
                    if float(dx.abs().max()) <= tol:
                        break
            return x - xp.solve(J.detach(), core.rhs(prep, x, u))
        x = np.array(T, dtype=float)
        for _ in range(max_iter):
            J = self._jac(prep, x, u)
            dx = xp.solve(J, core.rhs(prep, x, u))
            x = x - dx
            if np.max(np.abs(dx)) <= tol:
                break
        return x


def compile(net: Network, backend: str = "jax", dtype: str = "float64",  # noqa: A001
            torch_threads: int | None = 1, torch_compile: bool | None = None) -> Model:
    """Compile a validated network for ``backend`` (``"jax"`` or ``"torch"``; ``"numpy"`` is a reference
    backend without autodiff) in ``dtype`` (``"float64"`` default, or ``"float32"``).

    ``torch_threads``: for the torch backend, the number of intra-op threads torch is set to
    (``torch.set_num_threads``; a process-wide setting). Thermal networks are small, so extra threads only
    add synchronisation: a batched case-study step measured 47× slower with torch's default 2 threads than
    with 1 on a 2-core machine (benchmarks/bench_rollout.py ``--torch-threads``). ``None`` leaves torch's
    setting alone. The environment variable ``TNN_TORCH_THREADS`` overrides the default.

    ``torch_compile``: for the torch backend, run each integration step of a rollout through
    ``torch.compile`` (inductor). Measured on the case study M3 (benchmarks/bench_rollout.py, BENCHMARKS.md):
    a single sequence 3.1× faster than eager, a batch of 256 windows 1.1× (forward) and 1.3×
    (forward+gradient), after 13–33 s of compilation; M2's training 2.5× faster in all
    (benchmarks/bench_train.py). Worth it for training runs of minutes, not for one short simulation. ``None`` reads the environment variable ``TNN_TORCH_COMPILE`` (``1``/``0``,
    default off). Ignored by the other backends (JAX is always compiled)."""
    if backend not in ("jax", "torch", "numpy"):
        raise TnnError([Diagnostic(f"unknown backend {backend!r}", hint="use backend='jax' or backend='torch'")])
    if dtype not in ("float64", "float32"):
        raise TnnError([Diagnostic(f"unknown dtype {dtype!r}", hint="use dtype='float64' or dtype='float32'")])
    if backend == "torch":
        env = os.environ.get("TNN_TORCH_THREADS")
        if env:
            if not env.isdigit() or int(env) < 1:
                raise TnnError([Diagnostic(f"TNN_TORCH_THREADS must be a positive integer, got {env!r}")])
            torch_threads = int(env)
        if torch_threads is not None:
            import torch

            if torch.get_num_threads() != int(torch_threads):
                torch.set_num_threads(int(torch_threads))
    if torch_compile is None:
        env = os.environ.get("TNN_TORCH_COMPILE", "").strip()
        if env not in ("", "0", "1"):
            raise TnnError([Diagnostic(f"TNN_TORCH_COMPILE must be 0 or 1, got {env!r}")])
        torch_compile = env == "1"
    return Model(net, backend, dtype, torch_compile=bool(torch_compile))


__all__ = ["compile", "Model", "ParamSpec", "TorchCompileWarning"]
