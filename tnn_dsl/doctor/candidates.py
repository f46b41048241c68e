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
* ``thermal_mass`` — a missing thermal mass on a link a–b (a building envelope, a heat-pipe wall): a new
  node ``m_<a>_<b>`` of capacity ``C_m`` between a and b, the link split into a–m and m–b with ``f·R`` and
  ``(1−f)·R`` (same total resistance, so the same steady state). At small ``C_m`` it is an extra heat flow
  ``−C_m·(1−f)·dT_m/dt`` into a and ``−C_m·f·dT_m/dt`` into b (:func:`mass_forcing`); the proper fit frees
  ``C_m`` and ``f``.
* ``source_mass`` — a missing heat capacity behind a heat source (a heater's or radiator's own mass, Bacher &
  Madsen's TiTh): the source heats a new node ``m_<source>`` of capacity ``C_h`` joined to its node by ``R_h``
  instead of heating the node directly. The steady state is the original one; in transients the node receives
  the source's heat through a first-order lag ``τ = C_h·R_h`` (:func:`source_lag_forcing`); the proper fit
  frees ``C_h`` and ``R_h``.

All edited networks are built as IR directly (the validation pass would refuse a zero conductance);
:func:`clause_text` gives the ``.thn`` text of a candidate at its fitted value.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

from ..ir import (
    Binary,
    LearnFunction,
    LearnInput,
    LearnTarget,
    Link,
    Network,
    Num,
    Param,
    Radiation,
    Ref,
    Temp,
    ThermalNode,
    walk,
)

__all__ = ["Column", "Candidate", "Extended", "build_extended", "refs_in", "var_label", "fn_name",
           "structural_candidates", "apply_structural", "mass_forcing", "mass_grid", "mass_values", "mass_lines", "STRUCTURAL_KINDS",
           "MASS_FRACTION_BOUNDS", "source_lag_forcing", "source_tau_grid", "source_mass_values", "source_mass_lines",
           "source_line_moved"]

STRUCTURAL_KINDS = ("sensor_lag", "thermal_mass", "source_mass")
MASS_FRACTION_BOUNDS = (0.05, 0.95)
"""Bounds of a thermal-mass candidate's ``f`` (the share of the split link's resistance on the ``a`` side):
at f → 0 or 1 the new node merges into a neighbour and its capacity stops being identifiable."""

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
            "thermal_mass": f"missing thermal mass between {self.element.get('a', '')} and"
            f" {self.element.get('b', '')} (on link {self.element.get('link', '')})",
            "source_mass": f"missing heat capacity behind source {self.target} (between it and node"
            f" {self.element.get('at', '')})",
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


def _unique_name(name: str, taken: set[str]) -> str:
    """``name``, or ``name_2``, ``name_3`` … the first not in ``taken``; the result is added to ``taken``
    (names the doctor adds to a network never shadow the user's)."""
    base, i = name, 2
    while name in taken:
        name = f"{base}_{i}"
        i += 1
    taken.add(name)
    return name


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
        return _unique_name(name, pnames)

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
                # the bias comes with every dependence: the inputs are centred on their mid-range, so a
                # law ``a·v`` (a heat load driven by a column that is 0 when off) needs the offset too
                cands.append(Candidate(kind, tgt, [var_label(k, v)], [Column(f"{fname}.W", i * n_out + j)] + bias,
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


def _mass_ends(net: Network, link: Link) -> tuple[str, str]:
    """The order ``(a, b)`` of a thermal-mass candidate's target ``a--b``: a node before a boundary; between two
    nodes, a sensed node first (the mass sits "behind" what is measured), then declaration order."""
    nodes = net.node_names
    if link.a not in nodes:
        return link.b, link.a
    if link.b not in nodes:
        return link.a, link.b
    sensed = {s.node for s in net.sensors}
    return tuple(sorted((link.a, link.b), key=lambda n: (n not in sensed, nodes.index(n))))  # type: ignore[return-value]


def _mass_skip(net: Network, link: Link, learned: dict) -> bool:
    """True for links a thermal-mass candidate cannot split cleanly (see :func:`structural_candidates`)."""
    if link.value in learned:
        # the value is a learned function's output: the function is fitted on the whole link; splitting it would
        # need the function on two links (and its training data describe the unsplit link)
        return True
    try:
        p = net.param(link.value)
    except KeyError:
        return True
    if not p.is_constant or not p.value or p.value <= 0:
        # a derived value (a law in inputs, temperatures or other parameters, e.g. 1/(h·A(T))): which of its
        # factors belongs to which side of the new node is not determined by the link; zero or negative
        # values are not conduction paths
        return True
    if "." in link.name or link.name.startswith("G_dx_"):
        # a link inside a subnet instance is written once for every instance (its text cannot be split for one
        # instance); G_dx_ links are the doctor's own candidate links
        return True
    main = net.source_files[0] if net.source_files else None
    if link.span is not None and main is not None and link.span.file != main:
        return True  # written in an included file: the extension cannot edit that line
    return False


def structural_candidates(net: Network, kinds: tuple[str, ...] | None = None) -> list[Candidate]:
    """Candidates that are not exactly null (see module doc): one ``sensor_lag`` per sensor without a lag and
    one ``thermal_mass`` per link (R or G, node–node or node–boundary) whose value is a positive constant (free
    or fixed); links whose value is learned or a derived expression, or written inside a subnet or an
    included file, are skipped (:func:`_mass_skip` says why). Their ``columns`` name the parameters the edited
    network gets (:func:`apply_structural`): ``[lag]``, or ``[C_m, f]`` for a thermal mass."""
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
    if "thermal_mass" in kinds:
        learned = net.learned_targets()
        taken = set(net.param_names) | set(net.node_names) | set(net.boundary_names) | {l.name for l in net.links}
        taken |= set(net.input_names)

        def unique(name: str) -> str:
            return _unique_name(name, taken)

        for link in net.links:
            if _mass_skip(net, link, learned):
                continue
            a, b = _mass_ends(net, link)
            m = unique(f"m_{a}_{b}")
            cap, frac = unique(f"C_{m}"), unique(f"f_{m}")
            l1, l2 = unique(f"{link.form}_{a}_{m}"), unique(f"{link.form}_{m}_{b}")
            out.append(Candidate("thermal_mass", f"{a}--{b}", [], [Column(cap, 0), Column(frac, 0)],
                                 element={"a": a, "b": b, "link": link.name, "value": link.value, "form": link.form,
                                          "node": m, "param": cap, "frac": frac, "links": [l1, l2]}))
    if "source_mass" in kinds:
        learned = net.learned_targets()
        taken = set(net.param_names) | set(net.node_names) | set(net.boundary_names) | {l.name for l in net.links}
        taken |= set(net.input_names)
        main = net.source_files[0] if net.source_files else None
        for src in net.sources:
            if src.node not in net.node_names or src.value in learned or "." in src.name:
                continue  # a boundary, a learned heat flow, or written once for every subnet instance
            if src.span is None or (main is not None and src.span.file != main):
                continue  # no line to edit (built by a tool, or in an included file)
            if not _varies_with_inputs(net, src.value):
                continue  # a constant heat load: a lag behind it is invisible
            m = _unique_name(f"m_{src.name}", taken)
            cap, res = _unique_name(f"C_{m}", taken), _unique_name(f"R_{m}", taken)
            out.append(Candidate("source_mass", src.name, [], [Column(cap, 0), Column(res, 0)],
                                 element={"source": src.name, "at": src.node, "value": src.value, "node": m,
                                          "param": cap, "res": res, "link": res}))
    return out


def _varies_with_inputs(net: Network, pname: str, depth: int = 0) -> bool:
    """Whether parameter ``pname``'s value depends on an input (directly or through other parameters)."""
    if depth > 64:
        return False
    try:
        p = net.param(pname)
    except KeyError:
        return pname in net.input_names
    for r in refs_in(p.expr):
        if r in net.input_names or (r != pname and _varies_with_inputs(net, r, depth + 1)):
            return True
    return False


_J_PER_K = {"kg": 1.0, "m": 2.0, "s": -2.0, "K": -1.0}


def apply_structural(net: Network, cand: Candidate, value: float, lower: float | None = None,
                     frac: float = 0.5, resistance: float | None = None,
                     resistance_lower: float | None = None) -> Network:
    """``net`` with the structural candidate ``cand`` built in, its new parameter(s) ``free``.

    * ``sensor_lag``: the lag ``value`` (s), bounded below by ``lower``.
    * ``thermal_mass``: a node ``m`` of capacity ``value`` (J/K, bounded below by ``lower``) between ``a`` and
      ``b``; the link a–b (value ``P``, a constant) becomes a–m and m–b, ``f·P`` and ``(1−f)·P`` for a resistance,
      ``P/f`` and ``P/(1−f)`` for a conductance (derived parameters: ``P`` stays in the table, free if it was),
      ``f = frac`` free in :data:`MASS_FRACTION_BOUNDS`. The total resistance is ``P`` for every ``f``, so the
      steady state is the original one. The new node is the last state; the links take the place of the old
      one in ``links``.
    * ``source_mass``: a node ``m`` of capacity ``value`` (J/K, bounded below by ``lower``) that the source now
      heats, joined to the source's node by a resistance ``resistance`` (K/W, free, bounded below by
      ``resistance_lower``; the link is appended to ``links``). Same steady state; the new node is the last
      state."""
    if cand.kind == "sensor_lag":
        lag = cand.element["param"]
        dim = {"s": 1.0}
        p = Param(name=lag, expr=Num(value=float(value), dim=dim, unit="s"), dim=dim, unit="s", role="time_constant",
                  free=True, lower=lower, owner=f"sensor {cand.target}")
        sensors = [s.model_copy(update={"lag": lag}) if s.name == cand.target else s for s in net.sensors]
        return net.model_copy(update={"params": list(net.params) + [p], "sensors": sensors}, deep=True)
    if cand.kind == "thermal_mass":
        el = cand.element
        a, b, m, pv = el["a"], el["b"], el["node"], el["value"]
        old = next((l for l in net.links if l.name == el["link"]), None)
        if old is None:
            raise ValueError(f"no link {el['link']!r} in network {net.name!r}")
        base = net.param(pv)
        f_lo, f_hi = MASS_FRACTION_BOUNDS
        ref_f, ref_p = Ref(name=el["frac"], kind="param"), Ref(name=pv, kind="param")
        one_minus_f = Binary(op="-", left=Num(value=1.0), right=ref_f)
        if old.form == "R":
            e1, e2 = Binary(op="*", left=ref_f, right=ref_p), Binary(op="*", left=one_minus_f, right=ref_p)
        else:
            e1, e2 = Binary(op="/", left=ref_p, right=ref_f), Binary(op="/", left=ref_p, right=one_minus_f)
        role = "resistance" if old.form == "R" else "conductance"
        l1, l2 = el["links"]
        new = [
            Param(name=el["param"], expr=Num(value=float(value), dim=_J_PER_K, unit="J/K"), dim=_J_PER_K, unit="J/K",
                  role="capacitance", free=True, lower=lower, owner=f"node {m}"),
            Param(name=el["frac"], expr=Num(value=float(frac)), role="generic", free=True, lower=f_lo, upper=f_hi,
                  label=f"share of {old.name}'s resistance on the {a} side of {m}"),
            Param(name=l1, expr=e1, dim=dict(base.dim), unit=base.unit, role=role, owner=f"link {l1}"),
            Param(name=l2, expr=e2, dim=dict(base.dim), unit=base.unit, role=role, owner=f"link {l2}"),
        ]
        links = []
        for l in net.links:
            if l.name == old.name:
                links += [Link(name=l1, a=a, b=m, form=old.form, value=l1),
                          Link(name=l2, a=m, b=b, form=old.form, value=l2)]
            else:
                links.append(l)
        node = ThermalNode(name=m, capacitance=el["param"], label="thermal mass found by the model doctor")
        return net.model_copy(update={"params": list(net.params) + new, "links": links,
                                      "nodes": list(net.nodes) + [node]}, deep=True)
    if cand.kind == "source_mass":
        el = cand.element
        if resistance is None or not resistance > 0:
            raise ValueError("a source_mass edit needs resistance > 0 (K/W)")
        m, at = el["node"], el["at"]
        if not any(sr.name == el["source"] for sr in net.sources):
            raise ValueError(f"no source {el['source']!r} in network {net.name!r}")
        r_dim = {"kg": -1.0, "m": -2.0, "s": 3.0, "K": 1.0}  # K/W
        new = [
            Param(name=el["param"], expr=Num(value=float(value), dim=_J_PER_K, unit="J/K"), dim=_J_PER_K, unit="J/K",
                  role="capacitance", free=True, lower=lower, owner=f"node {m}"),
            Param(name=el["res"], expr=Num(value=float(resistance), dim=r_dim, unit="K/W"), dim=r_dim, unit="K/W",
                  role="resistance", free=True, lower=resistance_lower, owner=f"link {el['link']}"),
        ]
        sources = [sr.model_copy(update={"node": m}) if sr.name == el["source"] else sr for sr in net.sources]
        node = ThermalNode(name=m, capacitance=el["param"],
                           label=f"heat capacity behind source {el['source']}, found by the model doctor")
        link = Link(name=el["link"], a=m, b=at, form="R", value=el["res"])
        return net.model_copy(update={"params": list(net.params) + new, "links": list(net.links) + [link],
                                      "nodes": list(net.nodes) + [node], "sources": sources}, deep=True)
    raise ValueError(f"not a structural candidate kind: {cand.kind}")


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


def _in_unit(value_si: float, unit: str | None, fallback: str) -> str:
    """``value_si`` written as a ``.thn`` quantity in ``unit`` (the unit the file wrote), else in ``fallback`` (SI)."""
    from ..lang import unit_scale

    if unit:
        try:
            scale, offset = unit_scale(unit)
            if offset == 0.0 and scale > 0:
                return f"{value_si / scale:.6g} {unit}"
        except Exception:  # noqa: BLE001 - an unusual unit text: write SI
            pass
    return f"{value_si:.6g} {fallback}"


def _scalar(params: dict, name: str, net: Network) -> float:
    if name in params:
        return float(np.asarray(params[name]).reshape(-1)[0])
    return float(net.param(name).value)


def mass_values(net: Network, cand: Candidate, params: dict) -> dict:
    """A fitted thermal mass in SI: ``C`` (J/K), ``f`` (share of the resistance on a's side), ``R`` (the split
    link's total resistance, K/W) and ``tau`` (s), the new node's own time constant ``C·f(1−f)·R``.
    ``net`` is a network holding the edit, ``params`` its numpy parameter values."""
    el = cand.element
    c = _scalar(params, el["param"], net)
    f = _scalar(params, el["frac"], net)
    v = _scalar(params, el["value"], net)
    r = v if el["form"] == "R" else (1.0 / v if v else float("inf"))
    return {"C": c, "f": f, "R": r, "tau": c * f * (1.0 - f) * r}


def mass_lines(net: Network, cand: Candidate, params: dict) -> list[str]:
    """The ``.thn`` statements of a fitted thermal mass (``net`` holds the edit, ``params`` its values): the split
    link's value as a ``param`` (same name, the file's unit, ``free`` as it was), the share ``f`` (free), the new
    node (``C`` in the unit of its neighbour's capacity, free) and the two links replacing the original one.
    The caller comments the original link line out."""
    el = cand.element
    a, b, m, form = el["a"], el["b"], el["node"], el["form"]
    pv = net.param(el["value"])
    vals = mass_values(net, cand, params)
    fallback = "K/W" if form == "R" else "W/K"
    v = _scalar(params, pv.name, net)
    free = ""
    if pv.free:
        free = "  free"
        if pv.lower is not None and pv.upper is not None:
            free += f" in [{_in_unit(pv.lower, pv.unit, fallback)}, {_in_unit(pv.upper, pv.unit, fallback)}]"
    cap_unit = None
    for n in net.nodes:
        if n.name == a:
            cap_unit = net.param(n.capacitance).unit
    fl = el["frac"]
    f_lo, f_hi = MASS_FRACTION_BOUNDS
    l1, l2 = el["links"]
    if form == "R":
        e1, e2 = f"{fl} * {pv.name}", f"(1 - {fl}) * {pv.name}"
    else:
        e1, e2 = f"{pv.name} / {fl}", f"{pv.name} / (1 - {fl})"
    return [
        f"param {pv.name} = {_in_unit(v, pv.unit, fallback)}{free}  \"total of the links {a}–{m}–{b}\"",
        f"param {fl} = {vals['f']:.4g}  free in [{f_lo:g}, {f_hi:g}]  \"share of {pv.name} on the {a} side\"",
        f"node {m} \"thermal mass found by tnnc diagnose\"  C = {_in_unit(vals['C'], cap_unit, 'J/K')}  free",
        f"{form} {a} -- {m} = {e1}  as {l1}",
        f"{form} {m} -- {b} = {e2}  as {l2}",
    ]


# ---------------------------------------------------------------------------------------------
# source_mass: a heat capacity behind a source
# ---------------------------------------------------------------------------------------------


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


def source_mass_values(net: Network, cand: Candidate, params: dict) -> dict:
    """A fitted capacity behind a source in SI: ``C`` (J/K), ``R`` (K/W) and ``tau = C·R`` (s)."""
    el = cand.element
    c = _scalar(params, el["param"], net)
    r = _scalar(params, el["res"], net)
    return {"C": c, "R": r, "tau": c * r}


def source_mass_lines(net: Network, cand: Candidate, params: dict) -> list[str]:
    """The ``.thn`` statements of a fitted capacity behind a source (``net`` holds the edit): the new node (``C``
    in the unit of the heated node's capacity) and its resistance to that node (in the file's resistance unit
    where it has one). The source's own line is edited by :func:`source_line_moved`."""
    el = cand.element
    v = source_mass_values(net, cand, params)
    cap_unit = None
    for nd in net.nodes:
        if nd.name == el["at"]:
            cap_unit = net.param(nd.capacitance).unit
    r_unit = None
    for l in net.links:
        if l.form == "R" and l.name != el["link"]:
            try:
                r_unit = net.param(l.value).unit or r_unit
            except KeyError:
                pass
            if r_unit:
                break
    return [
        f"node {el['node']} \"heat capacity behind source {el['source']}, found by tnnc diagnose\"  "
        f"C = {_in_unit(v['C'], cap_unit, 'J/K')}  free",
        f"R {el['node']} -- {el['at']} = {_in_unit(v['R'], r_unit, 'K/W')}  free  as {el['res']}",
    ]


def source_line_moved(line: str, cand: Candidate) -> str | None:
    """The ``source <node> = …`` line of ``cand``'s source with the heated node replaced by the new node (None
    if the line does not have that form)."""
    el = cand.element
    pat = re.compile(r"^(\s*source\s+)" + re.escape(el["at"]) + r"(\s*=)")
    if not pat.search(line):
        return None
    return pat.sub(lambda m: m.group(1) + el["node"] + m.group(2), line, count=1)
