"""The exactly-null candidate deficiencies as IR edits, for the model doctor (structural ones:
:mod:`.structural`; the candidate types: :mod:`.base`).

Every candidate here is *exactly null*: at zero value of its new parameters the extended network computes
the same trajectories as the original one. That is what lets the diagnosis hold all of them in ONE
extended network, compile it once and rank them by a score (Lagrange-multiplier) test at the fitted
nominal point.

Candidates come from the IR (not from a list of names):

* ``param_dependence`` — a parameter P (R, G, C, component coefficient, source value, generic param)
  depends on a variable v (an input, or the temperature of a node of P's own element; a capacity only on its node's
  temperature): ``learn P as linear(v)``; columns ``dx_P.W[v]`` and ``dx_P.b``. Curved shapes (this kind and
  ``heat_load``): the square ``v²`` or a product ``v·w``, one column of the same function made a ``poly`` of degree
  2 (:meth:`_Extension.curved_shapes`), scored once the linear ``v`` (or ``w``) of the target is accepted.
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
:mod:`.extension` gives the ``.thn`` text of a candidate at its fitted value.
"""

from __future__ import annotations

from ..compiler.learned import monomial_index
from ..ir import LearnFunction, LearnInput, LearnTarget, Link, Network, Num, Param, Radiation, Ref
from .base import _AREA_DIM, _DEP_ROLES, _GK_DIM, _K_DIM, Candidate, Column, Extended, _unique_name, refs_in, var_label

__all__ = ["build_extended", "product_partners"]


def _element_params(net: Network):
    """``(parameter name or None, nodes/boundaries)`` for every parameter field of every element of ``net``."""
    for n in net.nodes:
        yield n.capacitance, (n.name,)
    for b in net.boundaries:
        yield b.temperature, (b.name,)
    for l in net.links:
        yield l.value, (l.a, l.b)
    for r in net.radiations:
        for p in (r.area, r.emissivity, r.view_factor):
            yield p, (r.a, r.b)
    for pe in net.peltiers:
        for p in (pe.current, pe.seebeck, pe.resistance, pe.r_internal):
            yield p, (pe.hot, pe.cold)
    for f in net.fluids:
        for p in (f.inlet, f.mdot, f.cp, f.ua):
            yield p, (f.node,)
    for s in net.sources:
        yield s.value, (s.node,)
    for s in net.sensors:
        yield s.lag, (s.node,)
        yield s.offset, (s.node,)


def product_partners(net: Network) -> dict[str, str]:
    """Parameters that enter ``net`` only as a product with one other: a fluid's ``mdot`` and ``cp`` (its
    heat-capacity rate ṁ·c_p, :func:`tnn_dsl.compiler.physics.fluid_conductance`), each a fixed constant used by
    that fluid alone (no other element, no parameter expression, no ``learn`` clause reads or targets it). Maps each to
    its partner. A dependence or a wrong value of one is then the same model as the same dependence of the other
    (written ``nominal + y_scale·z``, ``y_scale`` the nominal: ṁ(1 + z)·c_p = ṁ·c_p(1 + z)); the doctor fits it
    once (:meth:`tnn_dsl.doctor.session._Session.fit_exact`)."""
    fields: dict[str, int] = {}
    for p, _ in _element_params(net):
        if p:
            fields[p] = fields.get(p, 0) + 1
    read = {r for p in net.params for r in refs_in(p.expr)}
    read |= {li.name for fn in net.learned for li in fn.inputs}
    learned = set(net.learned_targets())
    const = {p.name for p in net.params if isinstance(p.expr, Num) and not p.free and not p.per_experiment}
    out: dict[str, str] = {}
    for f in net.fluids:
        m, c = f.mdot, f.cp
        if (m and c and m != c and all(fields.get(x) == 1 and x in const and x not in read and x not in learned
                                       for x in (m, c))):
            out[m], out[c] = c, m
    return out


def _param_nodes(net: Network) -> dict[str, set[str]]:
    """Parameter name → the nodes/boundaries of the element(s) that use it (directly or through a derived
    parameter's expression)."""
    use: dict[str, set[str]] = {}
    for p, nodes in _element_params(net):
        if p:
            use.setdefault(p, set()).update(nodes)
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


def _heat_inputs(net: Network) -> dict[str, set[str]]:
    """The network's *heat inputs* — inputs that only set heat sources (a heater command, a heating power): every
    parameter reading one, directly or through another parameter, is a source's heat flow, and no ``learn`` clause
    reads it. Maps each to the parameters that meet it in those sources' expressions (``Q1 → {Q_src_h1, a1}``)."""
    exprs = {p.name: p.expr for p in net.params}
    roles = {p.name: p.role for p in net.params}
    direct = {name: refs_in(e) for name, e in exprs.items()}
    learned_inputs = {li.name for fn in net.learned for li in fn.inputs if li.kind == "input"}
    out: dict[str, set[str]] = {}
    for i in net.input_names:
        users = {n for n, r in direct.items() if i in r}
        grew = True
        while grew:  # parameters reading a parameter that reads the input read it too
            more = {n for n, r in direct.items() if r & users} - users
            grew = bool(more)
            users |= more
        if users and i not in learned_inputs and all(roles[u] == "heat_flow" for u in users):
            out[i] = users | {r for u in users for r in direct[u] if r in exprs}
    return out


def _neighbours(net: Network) -> dict[str, set[str]]:
    g = net.graph()
    return {n: set(g.neighbors(n)) for n in g.nodes}


ALL_NULL_KINDS = ("param_dependence", "wrong_constant", "heat_load", "missing_link", "radiation", "sensor_offset",
                  "unused_column")


def build_extended(net: Network, varying_inputs: list[str], extra_inputs: list[str] | None = None,
                   kinds: tuple[str, ...] | None = None, only: set[str] | None = None,
                   shapes: bool = True) -> Extended:
    """Every exactly-null candidate of ``net`` in one extended network.

    ``varying_inputs`` are the inputs that vary in the training data (only those can explain anything);
    ``extra_inputs`` are names of inputs already added to ``net`` for data columns the model did not use
    (they drive heat-load candidates only). ``kinds`` restricts the candidate kinds. ``only`` (a set of
    :attr:`Candidate.key`) builds the small network holding just those candidates (the proper fits and
    the final extension use it; ``only=set()`` is the original network). ``shapes``: also the quadratic and
    product dependences (:meth:`_Extension.curved_shapes`)."""
    b = _Extension(net, varying_inputs, extra_inputs, kinds or ALL_NULL_KINDS, only, shapes)
    if "param_dependence" in b.kinds or "wrong_constant" in b.kinds:
        b.parameter_dependences()
    if "heat_load" in b.kinds or "unused_column" in b.kinds:
        b.heat_loads()
    if "missing_link" in b.kinds:
        b.missing_links()
    if "radiation" in b.kinds:
        b.radiation()
    if "sensor_offset" in b.kinds:
        b.sensor_offsets()
    if "param_dependence" in b.kinds:
        b.learned_constants()
    return b.extended()


class _Extension:
    """The extended network under construction: copies of the network's element lists that the candidate
    kinds add to, and the candidates with their columns."""

    def __init__(self, net: Network, varying_inputs: list[str], extra_inputs: list[str] | None,
                 kinds: tuple[str, ...], only: set[str] | None, shapes: bool = True):
        self.net, self.kinds, self.only = net, kinds, only
        self.extra_inputs = list(extra_inputs or [])
        self.varying = [i for i in varying_inputs if i not in self.extra_inputs]
        self.node_names = set(net.node_names)
        self.learned = net.learned_targets()
        self.input_names = set(net.input_names)
        self.pnodes = _param_nodes(net)
        self.neigh = _neighbours(net)
        self.heat_inputs = _heat_inputs(net)
        self.sensor_params = {s.lag for s in net.sensors} | {s.offset for s in net.sensors}
        self.params = list(net.params)
        self.pnames = {p.name for p in self.params}
        self.learned_fns = list(net.learned)
        self.links = list(net.links)
        self.radiations = list(net.radiations)
        self.sensors = list(net.sensors)
        self.cands: list[Candidate] = []
        self.fn_vars: dict[str, list[tuple[str, str]]] = {}
        self.replaced: dict[str, str] = {}
        self.shapes = shapes

    def keep(self, kind: str, target: str, dep: str = "") -> bool:
        return self.only is None or f"{kind}:{target}:{dep}" in self.only

    def inputs_for(self, p: Param) -> list[str]:
        """The varying inputs parameter ``p`` may depend on: a heat input (:func:`_heat_inputs`) changes the heat of
        its own source, not a conductance, a capacity or another source's gain — only a source's heat flow and the
        parameters of its own expression may depend on it (``a1 ~ Q1``: a heater's power not proportional to its
        command); every other input, for every parameter."""
        return [i for i in self.varying
                if i not in self.heat_inputs or p.role == "heat_flow" or p.name in self.heat_inputs[i]]

    def wanted(self, kind: str, target: str, label: str, others: list[str]) -> bool:
        """Whether variable ``label`` of ``target`` is needed: its linear, quadratic or a product candidate is kept
        (a product with a data column counts under either kind)."""
        deps = [label, f"{label}²"] + [f"{a}·{b}" for a, b in ((label, o) for o in others)] \
            + [f"{a}·{b}" for a, b in ((o, label) for o in others)]
        kinds = {kind, "unused_column", "heat_load", "param_dependence"}
        return any(self.keep(kd, target, d) for kd in kinds for d in deps)

    def unique(self, name: str) -> str:
        return _unique_name(name, self.pnames)

    def node_order(self, names) -> list[str]:
        return sorted(names, key=self.net.node_names.index)

    # -- one linear learned function holding many candidates ---------------------------------------

    def _dependence_kind(self, k: str, v: str, target_kind: str) -> str:
        """A heat load driven by an unused data column is ``unused_column``; a parameter depending on one (a fan's
        command changing a conductance) is a ``param_dependence`` like any other."""
        if target_kind == "heat_load":
            return "unused_column" if k == "input" and v in self.extra_inputs else "heat_load"
        return "param_dependence"

    def add_function(self, fname: str, entries, target_kind: str) -> None:
        """``entries``: ``[(target name, [(kind, var)], with_bias)]`` → one linear function (a ``const`` if it
        has no variable) and its candidates. ``W[i, j]`` is the candidate "target j depends on variable i";
        every other entry stays 0, so the function is exactly null and the network compiles small."""
        const_kind = "heat_load" if target_kind == "heat_load" else "wrong_constant"

        def target(t: str) -> str:
            return f"Q[{t}]" if target_kind == "heat_load" else t

        if self.only is not None:
            kept = []
            for t, vs, with_bias in entries:
                vs2 = [(k, v) for k, v in vs if self.wanted(self._dependence_kind(k, v, target_kind), target(t),
                                                             var_label(k, v), [var_label(*w) for w in vs])]
                if vs2 or self.keep(const_kind, target(t)):
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
        targets = [LearnTarget(kind=target_kind, name=t) for t, _, _ in entries]
        curved = self.curved_shapes(fname, entries, union, target_kind, target) if union and self.shapes else []
        # with a curved candidate the function is a poly of degree 2 (its first-degree monomials are the linear
        # candidates' columns; at W = 0, b = 0 it is exactly null, like the linear one)
        row = ({tuple(int(a) for a in m): r for r, m in enumerate(monomial_index(len(union), 2))} if curved else None)
        if union:
            self.learned_fns.append(LearnFunction(name=fname, kind="poly" if curved else "linear",
                                                  degree=2 if curved else None, targets=targets,
                                                  inputs=[LearnInput(kind=k, name=v) for k, v in union]))
            bias_key = f"{fname}.b"
        else:
            self.learned_fns.append(LearnFunction(name=fname, kind="const", targets=targets))
            bias_key = f"{fname}.c"
        self.fn_vars[fname] = union
        for j, (t, vs, with_bias) in enumerate(entries):
            bias = [Column(bias_key, j)] if with_bias else []
            if with_bias and const_kind in self.kinds:
                self.cands.append(Candidate(const_kind, target(t), [], list(bias), fn=fname, element={"output": j}))
            for k, v in vs:
                if not self.keep(self._dependence_kind(k, v, target_kind), target(t), var_label(k, v)):
                    continue  # kept for a curved shape only
                i = union.index((k, v))
                r = row[(0, i + 1)] if row else i
                # the bias comes with every dependence: the inputs are centred on their mid-range, so a
                # law ``a·v`` (a heat load driven by a column that is 0 when off) needs the offset too
                self.cands.append(Candidate(self._dependence_kind(k, v, target_kind), target(t), [var_label(k, v)],
                                            [Column(f"{fname}.W", r * n_out + j)] + bias, fn=fname, vars=[(k, v)],
                                            element={"output": j}))
        self.cands += curved

    def curved_shapes(self, fname: str, entries, union: list[tuple[str, str]], target_kind: str,
                      target) -> list[Candidate]:
        """Dependences beyond linear, as refinements of a linear one, in the same function (then a ``poly`` of
        degree 2 over the same variables): target j depends on the square of a variable v (``v²``) or on the
        product of two of its variables (``v·w``), one new column each (k = 1). A curved candidate is scored only
        once a linear dependence of the same target on one of its variables has been accepted
        (``element["parents"]``: the session's gate), so a flexible basis never outbids the physical candidates of
        a structured residual; the score test and the parameter charge then decide, and a target with an accepted
        curved term is written ``as poly(…; degree = 2)``."""
        mono = {tuple(int(a) for a in m): r for r, m in enumerate(monomial_index(len(union), 2))}
        n_out = len(entries)
        cands = []
        for j, (t, vs, _) in enumerate(entries):
            idx = [1 + union.index(v) for v in vs]
            parent = {v: f"{self._dependence_kind(*v, target_kind)}:{target(t)}:{var_label(*v)}" for v in vs}
            for a, (k, v) in zip(idx, vs):
                dep = f"{var_label(k, v)}²"
                kind = self._dependence_kind(k, v, target_kind)
                if self.keep(kind, target(t), dep):
                    cands.append(Candidate(kind, target(t), [dep], [Column(f"{fname}.W", mono[(a, a)] * n_out + j)],
                                           fn=fname, vars=[(k, v)],
                                           element={"output": j, "shape": "quadratic", "parents": [parent[(k, v)]]}))
            for x in range(len(vs)):
                for y in range(x + 1, len(vs)):
                    (k1, v1), (k2, v2) = vs[x], vs[y]
                    dep = f"{var_label(k1, v1)}·{var_label(k2, v2)}"
                    kind = ("unused_column" if target_kind == "heat_load" and any(
                        kk == "input" and vv in self.extra_inputs for kk, vv in (vs[x], vs[y]))
                        else self._dependence_kind(k1, v1, target_kind))
                    if self.keep(kind, target(t), dep):
                        a, b = sorted((idx[x], idx[y]))
                        cands.append(Candidate(kind, target(t), [dep], [Column(f"{fname}.W", mono[(a, b)] * n_out + j)],
                                               fn=fname, vars=[vs[x], vs[y]],
                                               element={"output": j, "shape": "product",
                                                        "parents": [parent[vs[x]], parent[vs[y]]]}))
        return cands

    # -- the kinds -----------------------------------------------------------------------------------

    def parameter_dependences(self) -> None:
        """Parameter dependence and wrong constants: ONE learned function ``dx_params`` over every eligible
        parameter; its inputs are the varying inputs, the data columns the network does not use (declared as inputs
        in the extension if a finding reads one) and the temperatures of the parameter's own element."""
        net, entries = self.net, []
        for p in net.params:
            if p.role not in _DEP_ROLES or p.name in self.learned or p.name in self.sensor_params:
                continue
            if isinstance(p.expr, Ref) and (p.expr.kind == "input" or p.expr.name in self.input_names):
                continue  # a slot bound to an input (a current, an inlet temperature): nothing to learn
            if p.role == "generic" and not self.pnodes.get(p.name):
                continue  # unused free-standing parameter
            if p.is_constant and p.value == 0.0 and p.role in ("resistance", "conductance", "capacitance"):
                continue
            vars_: list[tuple[str, str]] = []
            if "param_dependence" in self.kinds:
                # a heat capacity (m·c_p) may change with its node's temperature, never with a command or a
                # data column: such a "dependence" is only ever the compensation of something else
                vars_ = [] if p.role == "capacitance" else [("input", i) for i in self.inputs_for(p)]
                if p.role not in ("heat_flow", "capacitance"):  # a heat flow driven by an unused column is a
                    vars_ += [("input", c) for c in self.extra_inputs]  # heat load (its own family)
                vars_ += [("node", n) for n in self.node_order(self.pnodes.get(p.name, set()) & self.node_names)]
            with_bias = not p.free  # a free constant already moves along its own direction
            if vars_ or with_bias:
                entries.append((p.name, vars_, with_bias))
        self.add_function("dx_params", entries, "param")

    def heat_loads(self) -> None:
        """Heat loads, constant or depending on an input, the node's and its neighbours' temperatures, or a
        data column the network does not use: ``dx_Q``."""
        net, entries = self.net, []
        for n in net.node_names:
            if f"Q[{n}]" in self.learned:
                continue
            near = [n] + self.node_order((self.neigh.get(n, set()) & self.node_names) - {n})
            vars_ = [("input", i) for i in self.varying] + [("node", m) for m in near] if "heat_load" in self.kinds \
                else []
            if "unused_column" in self.kinds:
                vars_ += [("input", c) for c in self.extra_inputs]
            if vars_ or "heat_load" in self.kinds:
                entries.append((n, vars_, True))
        self.add_function("dx_Q", entries, "heat_load")

    def missing_links(self) -> None:
        """A conductance, from 0, between every node–node and node–boundary pair not already joined."""
        net = self.net
        verts = net.node_names + net.boundary_names
        joined = {frozenset((lk.a, lk.b)) for lk in net.links} | {frozenset((r.a, r.b)) for r in net.radiations}
        joined |= {frozenset((p.hot, p.cold)) for p in net.peltiers}
        for i, a in enumerate(net.node_names):
            for b in verts[i + 1:]:
                if frozenset((a, b)) in joined or a == b or not self.keep("missing_link", f"{a}--{b}"):
                    continue
                g = self.unique(f"G_dx_{a}_{b}")
                self.params.append(Param(name=g, expr=Num(value=0.0, dim=_GK_DIM, unit="W/K"), dim=_GK_DIM,
                                         unit="W/K", role="conductance", free=True, lower=0.0, owner=f"link {g}"))
                self.links.append(Link(name=g, a=a, b=b, form="G", value=g))
                self.cands.append(Candidate("missing_link", f"{a}--{b}", [], [Column(g, 0)],
                                            element={"a": a, "b": b, "param": g}))

    def radiation(self) -> None:
        """Grey-body radiation between every node and boundary, its emissivity·area from 0."""
        net = self.net
        have = {frozenset((r.a, r.b)) for r in net.radiations}
        for a in net.node_names:
            for b in net.boundary_names:
                if frozenset((a, b)) in have or not self.keep("radiation", f"{a}--{b}"):
                    continue
                name = f"rad_dx_{a}_{b}"
                area = self.unique(f"{name}.area")
                eps, vf = self.unique(f"{name}.emissivity"), self.unique(f"{name}.view_factor")
                self.params += [
                    Param(name=area, expr=Num(value=0.0, dim=_AREA_DIM, unit="m^2"), dim=_AREA_DIM, unit="m^2",
                          role="component", free=True, lower=0.0, owner=f"radiation {name}"),
                    Param(name=eps, expr=Num(value=1.0), role="component", owner=f"radiation {name}"),
                    Param(name=vf, expr=Num(value=1.0), role="component", owner=f"radiation {name}"),
                ]
                self.radiations.append(Radiation(name=name, a=a, b=b, area=area, emissivity=eps, view_factor=vf))
                self.cands.append(Candidate("radiation", f"{a}--{b}", [], [Column(area, 0)],
                                            element={"a": a, "b": b, "param": area}))

    def sensor_offsets(self) -> None:
        """A constant offset, from 0, on every sensor without one."""
        new_sensors = []
        for s in self.sensors:
            if s.offset is None and self.keep("sensor_offset", s.name):
                off = self.unique(f"{s.name}.offset")
                self.params.append(Param(name=off, expr=Num(value=0.0, dim=_K_DIM, unit="K"), dim=_K_DIM, unit="K",
                                         role="offset", free=True, owner=f"sensor {s.name}"))
                s = s.model_copy(update={"offset": off})
                self.cands.append(Candidate("sensor_offset", s.name, [], [Column(off, 0)],
                                            element={"sensor": s.name, "param": off}))
            new_sensors.append(s)
        self.sensors = new_sensors

    def learned_constants(self) -> None:
        """Learned constants that may depend on something (M1's ``learn R_hp1, R_hp2, R_hpa as const``): the const
        function becomes linear over the union of its targets' variables with W = 0 and b = c (exactly the
        same model); ``W[v, j]`` is the candidate "target j depends on v".

        A function of several targets also gets, for each variable that every one of its targets may depend on,
        the candidate "the function depends on v" (k = one column per target, :attr:`Candidate.members` its
        per-target parts): the user declared those targets one uncertain part, so the whole part may depend on the
        variable (``learn R_hp1, R_hp2, R_hpa as linear(u1)``) rather than one target standing in for the others
        (with one sensor on a series path, ``R_hp1`` alone absorbs ``R_hp2``'s dependence and the next rounds
        compensate elsewhere). The held-out test and the parameter charge decide between the two."""
        for fi, fn in enumerate(self.learned_fns):
            if fn.kind != "const" or fn.frozen or fn.init_from or fn.name.startswith("dx_"):
                continue
            if any(t.kind != "param" for t in fn.targets):
                continue
            group = ", ".join(t.name for t in fn.targets)
            possible = []
            for t in fn.targets:
                nodes = self.node_order(self.pnodes.get(t.name, set()) & self.node_names)
                possible.append([("input", i) for i in self.inputs_for(self.net.param(t.name))]
                                + [("node", n) for n in nodes])
            common = [v for v in possible[0] if all(v in tv for tv in possible)] if len(fn.targets) > 1 else []
            grouped = [v for v in common if self.keep("param_dependence", group, var_label(*v))]
            per_target = [[v for v in tv if self.keep("param_dependence", t.name, var_label(*v)) or v in grouped]
                          for t, tv in zip(fn.targets, possible)]
            union: list[tuple[str, str]] = [("input", i) for i in self.varying]
            for tv in per_target:
                union += [v for v in tv if v not in union]
            union = [v for v in union if any(v in tv for tv in per_target)]
            if not union:
                continue
            self.learned_fns[fi] = fn.model_copy(update={
                "kind": "linear", "inputs": [LearnInput(kind=k, name=v) for k, v in union]})
            self.replaced[fn.name] = "const"
            self.fn_vars[fn.name] = union
            n_out = len(fn.targets)

            def one(j: int, t: str, k: str, v: str) -> Candidate:
                return Candidate("param_dependence", t, [var_label(k, v)],
                                 [Column(f"{fn.name}.W", union.index((k, v)) * n_out + j)], fn=fn.name,
                                 vars=[(k, v)], element={"learned": fn.name, "output": j})

            for j, (t, tv) in enumerate(zip(fn.targets, per_target)):
                self.cands += [one(j, t.name, k, v) for k, v in tv
                               if self.keep("param_dependence", t.name, var_label(k, v))]
            for k, v in grouped:
                members = [one(j, t.name, k, v) for j, t in enumerate(fn.targets)]
                self.cands.append(Candidate("param_dependence", group, [var_label(k, v)],
                                            [m.columns[0] for m in members], fn=fn.name, vars=[(k, v)],
                                            element={"learned": fn.name, "members": members}))

    def extended(self) -> Extended:
        ext = self.net.model_copy(update={"params": self.params, "links": self.links, "radiations": self.radiations,
                                          "sensors": self.sensors, "learned": self.learned_fns}, deep=True)
        cand_keys = {c.key for cand in self.cands for c in cand.columns}
        return Extended(ext, self.cands, self.fn_vars, self.replaced, cand_keys)
