"""What the compiler records about a network, independent of any backend (:class:`_Plan`): the state, input and
parameter order, which parameters and learned functions are static or depend on inputs or node temperatures
(a topological order for both), links, radiation, components and sensors in index form, and flow names."""

from __future__ import annotations

import graphlib
from typing import Any

from ..core import Diagnostic, TnnError
from ..ir import Network
from .expressions import dependencies

NOMINAL_T = 298.15
"""K: the temperature at which nominal quantities (time constants, default normalisation) are taken."""


T_SCALE = 10.0
"""K: default normalisation scale of temperatures fed to learned functions."""


def _err(msg: str, span=None, hint: str | None = None) -> TnnError:
    return TnnError([Diagnostic(msg, span, hint)])


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
