"""Candidate model deficiencies as IR edits, for the model doctor (``_diagnose``).

Every candidate here is *exactly null*: at zero value of its new parameters the extended network computes
the same trajectories as the original one. That is what lets the diagnosis hold all of them in ONE
extended network, compile it once and rank them by a score (Lagrange-multiplier) test at the fitted
nominal point.

Candidates come from the IR (not from a list of names):

* ``param_dependence`` — a parameter P (R, G, C, component coefficient, source value, generic param)
  depends on a variable v (an input, or the temperature of a node of P's own element):
  ``learn P as linear(v)``; columns ``dx_P.W[v]`` and ``dx_P.b``.
* ``wrong_constant`` — a fixed parameter that is simply wrong: ``learn P as const``; column ``dx_P.b``.
* ``heat_load`` — an unmodelled heat load at node n, constant or depending on v (inputs, T(n) and its
  neighbours, data columns the model does not use): ``learn Q[n] as linear(v)``.
* ``missing_link`` — a conduction path a–b not in the network (nodes and boundaries not already joined):
  ``G a -- b = 0 W/K`` made free; column the new conductance.
* ``radiation`` — grey-body radiation node–boundary: emissivity·area starting at 0.
* ``sensor_offset`` — a constant offset on a sensor (its ``offset`` parameter, 0).

Not exactly null (a structural edit, :func:`structural_candidates` / :func:`apply_structural`):

* ``sensor_lag`` — a sensor without a lag reads its node through a first-order lag ``τ dT_s/dt = T_n − T_s``.
  At small τ the reading is ``T_n − τ·dT_n/dt``, so its score-test column is ``−dT_n/dt`` (a direct
  output term); the proper fit runs on the network with ``lag τ s free``.

All edited networks are built as IR directly (the validation pass would refuse a zero conductance);
:func:`clause_text` gives the ``.thn`` text of a candidate at its fitted value.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from ._ir import (
    Binary, Call, LearnFunction, LearnInput, LearnTarget, Link, Network, Num, Param, Radiation, Ref, Table,
    Temp, Unary, walk,
)

__all__ = ["Column", "Candidate", "Extended", "build_extended", "refs_in", "var_label", "fn_name",
           "structural_candidates", "apply_structural", "STRUCTURAL_KINDS"]

STRUCTURAL_KINDS = ("sensor_lag",)

# parameter roles a dependence / wrong-constant candidate may target
_DEP_ROLES = ("resistance", "conductance", "capacitance", "component", "heat_flow", "generic")
_K_DIM = {"K": 1.0}
_GK_DIM = {"kg": 1.0, "m": 2.0, "s": -3.0, "K": -1.0}  # W/K
_AREA_DIM = {"m": 2.0}


@dataclass(frozen=True)
class Column:
    """One scalar of the compiled model's parameter dict: ``params[key].ravel()[index]``."""

    key: str
    index: int = 0


@dataclass
class Candidate:
    """One exactly-null deficiency. ``columns`` are its new parameters (k = len(columns)).

    ``kind`` see module doc; ``target`` a parameter name, ``Q[node]``, ``a--b`` or a sensor name;
    ``depends_on`` the variables (input names or ``T(node)``) its value depends on."""

    kind: str
    target: str
    depends_on: list[str]
    columns: list[Column]
    fn: str | None = None  # the extended network's learned function holding it (param/heat-load kinds)
    vars: list[tuple[str, str]] = field(default_factory=list)  # (kind "node"|"input", name) for learn inputs
    element: dict = field(default_factory=dict)  # extra info (link ends, sensor, ...)

    @property
    def k(self) -> int:
        return len(self.columns)

    @property
    def key(self) -> str:
        dep = ",".join(self.depends_on)
        return f"{self.kind}:{self.target}:{dep}"

    def describe(self) -> str:
        words = {
            "param_dependence": f"{self.target} depends on {', '.join(self.depends_on)}",
            "wrong_constant": f"{self.target} has the wrong value",
            "heat_load": f"unmodelled heat load at {self.target[2:-1]}"
            + (f" depending on {', '.join(self.depends_on)}" if self.depends_on else " (constant)"),
            "missing_link": f"missing conduction path {self.target}",
            "radiation": f"missing radiation {self.target}",
            "sensor_offset": f"offset on sensor {self.target}",
            "sensor_lag": f"sensor {self.target} lags its node {self.element.get('node', '')}",
            "unused_column": f"heat load at {self.target[2:-1]} driven by unused data column"
            f" {', '.join(self.depends_on)}",
        }
        return words.get(self.kind, f"{self.kind} {self.target}")


@dataclass
class Extended:
    """The extended network (original + every candidate at its null value) and the candidates.
    ``stats`` holds, per learned function of the extension, the variables of its inputs in order."""

    network: Network
    candidates: list[Candidate]
    fn_vars: dict[str, list[tuple[str, str]]]
    replaced: dict[str, str] = field(default_factory=dict)
    """Learned functions of the original network whose kind the extension changed (name → old kind)."""
    candidate_keys: set[str] = field(default_factory=set)
    """Parameter-dict keys whose scalars are candidate columns (never fitted as nominal free params)."""


def refs_in(expr) -> set[str]:
    """Names referenced (``Ref``) in an expression tree."""
    return {e.name for e in walk(expr) if isinstance(e, Ref)}


def temps_in(expr) -> set[str]:
    """Nodes whose temperature (``Temp``) an expression reads."""
    return {e.node for e in walk(expr) if isinstance(e, Temp)}


def var_label(kind: str, name: str) -> str:
    """How a variable is named in findings: an input by its name, a node temperature as ``T(node)``."""
    return f"T({name})" if kind == "node" else name


def fn_name(target: str) -> str:
    """The extended network's learned-function name for a target (an identifier)."""
    return "dx_" + re.sub(r"[^A-Za-z0-9_]", "_", target)


def _param_nodes(net: Network) -> dict[str, set[str]]:
    """Parameter name → the nodes/boundaries of the element(s) that use it (directly or through a derived
    parameter's expression)."""
    use: dict[str, set[str]] = {}

    def add(p: str | None, *nodes: str):
        if p:
            use.setdefault(p, set()).update(nodes)

    for n in net.nodes:
        add(n.capacitance, n.name)
    for b in net.boundaries:
        add(b.temperature, b.name)
    for l in net.links:
        add(l.value, l.a, l.b)
    for r in net.radiations:
        for p in (r.area, r.emissivity, r.view_factor):
            add(p, r.a, r.b)
    for pe in net.peltiers:
        for p in (pe.current, pe.seebeck, pe.resistance, pe.r_internal):
            add(p, pe.hot, pe.cold)
    for f in net.fluids:
        for p in (f.inlet, f.mdot, f.cp, f.ua):
            add(p, f.node)
    for s in net.sources:
        add(s.value, s.node)
    for s in net.sensors:
        add(s.lag, s.node)
        add(s.offset, s.node)
    # propagate through derived parameters: a param referenced by P's expression is used where P is
    changed = True
    exprs = {p.name: p.expr for p in net.params}
    while changed:
        changed = False
        for name, expr in exprs.items():
            where = use.get(name)
            if not where:
                continue
            for r in refs_in(expr):
                if r in exprs and not where <= use.get(r, set()):
                    use.setdefault(r, set()).update(where)
                    changed = True
    return use


def _neighbours(net: Network) -> dict[str, set[str]]:
    g = net.graph()
    return {n: set(g.neighbors(n)) for n in g.nodes}


def build_extended(net: Network, varying_inputs: list[str], extra_inputs: list[str] | None = None,
                   kinds: tuple[str, ...] | None = None, only: set[str] | None = None) -> Extended:
    """Every exactly-null candidate of ``net`` in one extended network.

    ``varying_inputs`` are the inputs that vary in the training data (only those can explain anything);
    ``extra_inputs`` are names of inputs already added to ``net`` for data columns the model did not use
    (they drive heat-load candidates only). ``kinds`` restricts the candidate kinds. ``only`` (a set of
    :attr:`Candidate.key`) builds the small network holding just those candidates (the proper fits and
    the final extension use it; ``only=set()`` is the original network)."""

    def keep(kind: str, target: str, dep: str = "") -> bool:
        return only is None or f"{kind}:{target}:{dep}" in only
    kinds = kinds or ("param_dependence", "wrong_constant", "heat_load", "missing_link", "radiation",
                      "sensor_offset", "unused_column")
    extra_inputs = list(extra_inputs or [])
    varying = [i for i in varying_inputs if i not in extra_inputs]
    node_names = set(net.node_names)
    learned = net.learned_targets()
    input_names = set(net.input_names)
    pnodes = _param_nodes(net)
    neigh = _neighbours(net)
    sensor_params = {s.lag for s in net.sensors} | {s.offset for s in net.sensors}

    params = list(net.params)
    pnames = {p.name for p in params}
    learned_fns = list(net.learned)
    links = list(net.links)
    radiations = list(net.radiations)
    sensors = list(net.sensors)
    cands: list[Candidate] = []
    fn_vars: dict[str, list[tuple[str, str]]] = {}

    def unique(name: str) -> str:
        base, i = name, 2
        while name in pnames:
            name = f"{base}_{i}"
            i += 1
        pnames.add(name)
        return name

    # -- parameter dependence and wrong constants: ONE learned function "dx_params" -------------
    # targets: every eligible parameter; inputs: the union of their variables. W[i, j] is the candidate
    # "target j depends on variable i" (only for variables of j's own element and the inputs); every
    # other W entry stays 0, so the function is exactly null and the network compiles small.
    def add_function(fname, entries, target_kind):
        """entries: [(target name, [(kind, var)], with_bias)] → one linear function + its candidates."""
        if only is not None:
            kept = []
            for t, vs, with_bias in entries:
                tgt = f"Q[{t}]" if target_kind == "heat_load" else t
                const_kind = "heat_load" if target_kind == "heat_load" else "wrong_constant"
                vs2 = [(k, v) for k, v in vs if keep(
                    "unused_column" if (k == "input" and v in extra_inputs) else
                    ("heat_load" if target_kind == "heat_load" else "param_dependence"), tgt, var_label(k, v))]
                if vs2 or keep(const_kind, tgt):
                    kept.append((t, vs2, with_bias))
            entries = kept
        if not entries:
            return
        union: list[tuple[str, str]] = []
        for _, vs, _ in entries:
            for v in vs:
                if v not in union:
                    union.append(v)
        n_out = len(entries)
        if union:
            learned_fns.append(LearnFunction(
                name=fname, kind="linear",
                targets=[LearnTarget(kind=target_kind, name=t) for t, _, _ in entries],
                inputs=[LearnInput(kind=k, name=v) for k, v in union]))
            bias_key = f"{fname}.b"
        else:
            learned_fns.append(LearnFunction(
                name=fname, kind="const", targets=[LearnTarget(kind=target_kind, name=t) for t, _, _ in entries]))
            bias_key = f"{fname}.c"
        fn_vars[fname] = union
        for j, (t, vs, with_bias) in enumerate(entries):
            tgt = f"Q[{t}]" if target_kind == "heat_load" else t
            bias = [Column(bias_key, j)] if with_bias else []
            const_kind = "heat_load" if target_kind == "heat_load" else "wrong_constant"
            if with_bias and const_kind in kinds:
                cands.append(Candidate("heat_load" if target_kind == "heat_load" else "wrong_constant", tgt, [],
                                       list(bias), fn=fname, element={"output": j}))
            for k, v in vs:
                i = union.index((k, v))
                kind = "unused_column" if (k == "input" and v in extra_inputs) else (
                    "heat_load" if target_kind == "heat_load" else "param_dependence")
                extra_b = bias if kind != "unused_column" else []
                cands.append(Candidate(kind, tgt, [var_label(k, v)], [Column(f"{fname}.W", i * n_out + j)] + extra_b,
                                       fn=fname, vars=[(k, v)], element={"output": j}))

    if "param_dependence" in kinds or "wrong_constant" in kinds:
        entries = []
        for p in net.params:
            if p.role not in _DEP_ROLES or p.name in learned or p.name in sensor_params:
                continue
            if isinstance(p.expr, Ref) and (p.expr.kind == "input" or p.expr.name in input_names):
                continue  # a slot bound to an input (a current, an inlet temperature): nothing to learn
            if p.role == "generic" and not pnodes.get(p.name):
                continue  # unused free-standing parameter
            if p.is_constant and p.value == 0.0 and p.role in ("resistance", "conductance", "capacitance"):
                continue
            vars_: list[tuple[str, str]] = []
            if "param_dependence" in kinds:
                vars_ = [("input", i) for i in varying]
                vars_ += [("node", n) for n in sorted(pnodes.get(p.name, set()) & node_names, key=net.node_names.index)]
            with_bias = not p.free  # a free constant already moves along its own direction
            if not vars_ and not with_bias:
                continue
            entries.append((p.name, vars_, with_bias))
        add_function("dx_params", entries, "param")

    # -- heat loads (constant, depending on a variable, driven by an unused data column): "dx_Q" -----
    if "heat_load" in kinds or "unused_column" in kinds:
        entries = []
        for n in net.node_names:
            if f"Q[{n}]" in learned:
                continue
            near = [n] + sorted((neigh.get(n, set()) & node_names) - {n}, key=net.node_names.index)
            vars_ = [("input", i) for i in varying] + [("node", m) for m in near] if "heat_load" in kinds else []
            if "unused_column" in kinds:
                vars_ += [("input", c) for c in extra_inputs]
            if vars_ or "heat_load" in kinds:
                entries.append((n, vars_, True))
        add_function("dx_Q", entries, "heat_load")

    # -- missing links (node–node and node–boundary pairs not already joined) ------------------
    if "missing_link" in kinds:
        verts = net.node_names + net.boundary_names
        joined = {frozenset((l.a, l.b)) for l in net.links} | {frozenset((r.a, r.b)) for r in net.radiations}
        joined |= {frozenset((p.hot, p.cold)) for p in net.peltiers}
        for i, a in enumerate(net.node_names):
            for b in verts[i + 1:]:
                if frozenset((a, b)) in joined or a == b or not keep("missing_link", f"{a}--{b}"):
                    continue
                g = unique(f"G_dx_{a}_{b}")
                params.append(Param(name=g, expr=Num(value=0.0, dim=_GK_DIM, unit="W/K"), dim=_GK_DIM,
                                    unit="W/K", role="conductance", free=True, lower=0.0,
                                    owner=f"link {g}"))
                links.append(Link(name=g, a=a, b=b, form="G", value=g))
                cands.append(Candidate("missing_link", f"{a}--{b}", [], [Column(g, 0)],
                                       element={"a": a, "b": b, "param": g}))

    # -- radiation node–boundary (emissivity·area from 0) --------------------------------------
    if "radiation" in kinds:
        have = {frozenset((r.a, r.b)) for r in net.radiations}
        for a in net.node_names:
            for b in net.boundary_names:
                if frozenset((a, b)) in have or not keep("radiation", f"{a}--{b}"):
                    continue
                name = f"rad_dx_{a}_{b}"
                area, eps, vf = unique(f"{name}.area"), unique(f"{name}.emissivity"), unique(f"{name}.view_factor")
                params += [
                    Param(name=area, expr=Num(value=0.0, dim=_AREA_DIM, unit="m^2"), dim=_AREA_DIM, unit="m^2",
                          role="component", free=True, lower=0.0, owner=f"radiation {name}"),
                    Param(name=eps, expr=Num(value=1.0), role="component", owner=f"radiation {name}"),
                    Param(name=vf, expr=Num(value=1.0), role="component", owner=f"radiation {name}"),
                ]
                radiations.append(Radiation(name=name, a=a, b=b, area=area, emissivity=eps, view_factor=vf))
                cands.append(Candidate("radiation", f"{a}--{b}", [], [Column(area, 0)],
                                       element={"a": a, "b": b, "param": area}))

    # -- sensor offsets -------------------------------------------------------------------------
    if "sensor_offset" in kinds:
        new_sensors = []
        for s in sensors:
            if s.offset is None and keep("sensor_offset", s.name):
                off = unique(f"{s.name}.offset")
                params.append(Param(name=off, expr=Num(value=0.0, dim=_K_DIM, unit="K"), dim=_K_DIM, unit="K",
                                    role="offset", free=True, owner=f"sensor {s.name}"))
                s = s.model_copy(update={"offset": off})
                cands.append(Candidate("sensor_offset", s.name, [], [Column(off, 0)],
                                       element={"sensor": s.name, "param": off}))
            new_sensors.append(s)
        sensors = new_sensors

    # -- learned constants that may depend on something (M1's `learn R_hp1, R_hp2 as const`) ------
    # the const function becomes linear over the union of its targets' variables with W = 0 and b = c:
    # exactly the same model; W[v, j] is the candidate "target j depends on v".
    replaced: dict[str, str] = {}
    if "param_dependence" in kinds:
        for fi, fn in enumerate(learned_fns):
            if fn.kind != "const" or fn.frozen or fn.init_from or fn.name.startswith("dx_"):
                continue
            if any(t.kind != "param" for t in fn.targets):
                continue
            per_target = []
            union: list[tuple[str, str]] = [("input", i) for i in varying]
            for t in fn.targets:
                nodes = sorted(pnodes.get(t.name, set()) & node_names, key=net.node_names.index)
                tv = [("input", i) for i in varying] + [("node", n) for n in nodes]
                tv = [(k, v) for k, v in tv if keep("param_dependence", t.name, var_label(k, v))]
                per_target.append(tv)
                for v in tv:
                    if v not in union:
                        union.append(v)
            union = [v for v in union if any(v in tv for tv in per_target)]
            if not union:
                continue
            learned_fns[fi] = fn.model_copy(update={
                "kind": "linear", "inputs": [LearnInput(kind=k, name=v) for k, v in union]})
            replaced[fn.name] = "const"
            fn_vars[fn.name] = union
            n_out = len(fn.targets)
            for j, (t, tv) in enumerate(zip(fn.targets, per_target)):
                for k, v in tv:
                    i = union.index((k, v))
                    cands.append(Candidate("param_dependence", t.name, [var_label(k, v)],
                                           [Column(f"{fn.name}.W", i * n_out + j)], fn=fn.name, vars=[(k, v)],
                                           element={"learned": fn.name, "output": j}))

    ext = net.model_copy(update={"params": params, "links": links, "radiations": radiations,
                                 "sensors": sensors, "learned": learned_fns}, deep=True)
    cand_keys = {c.key for cand in cands for c in cand.columns}
    return Extended(ext, cands, fn_vars, replaced, cand_keys)


def _btemp(net: Network, boundary: str) -> str | None:
    for b in net.boundaries:
        if b.name == boundary:
            return b.temperature
    return None


def structural_candidates(net: Network, kinds: tuple[str, ...] | None = None) -> list[Candidate]:
    """Candidates that are not exactly null (see module doc): one ``sensor_lag`` per sensor without a lag.
    Their ``columns`` name the parameter the edited network gets (:func:`apply_structural`)."""
    kinds = kinds or STRUCTURAL_KINDS
    out: list[Candidate] = []
    if "sensor_lag" in kinds:
        names = {p.name for p in net.params}
        for sn in net.sensors:
            if sn.lag is not None or sn.node not in net.node_names:
                continue
            lag = f"{sn.name}.lag"
            if lag in names:
                continue
            out.append(Candidate("sensor_lag", sn.name, [], [Column(lag, 0)],
                                 element={"sensor": sn.name, "node": sn.node, "param": lag}))
    return out


def apply_structural(net: Network, cand: Candidate, value: float, lower: float | None = None) -> Network:
    """``net`` with the structural candidate ``cand`` built in, its new parameter ``free`` at ``value``
    (SI: seconds for a sensor lag), bounded below by ``lower``."""
    if cand.kind == "sensor_lag":
        lag = cand.element["param"]
        dim = {"s": 1.0}
        p = Param(name=lag, expr=Num(value=float(value), dim=dim, unit="s"), dim=dim, unit="s", role="time_constant",
                  free=True, lower=lower, owner=f"sensor {cand.target}")
        sensors = [s.model_copy(update={"lag": lag}) if s.name == cand.target else s for s in net.sensors]
        return net.model_copy(update={"params": list(net.params) + [p], "sensors": sensors}, deep=True)
    raise ValueError(f"not a structural candidate kind: {cand.kind}")
