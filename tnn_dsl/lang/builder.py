"""Statements to IR: scopes (subnet instances and their prefixes), declared names, units to SI, automatic
names, includes and subnets expanded, learned functions with their options; every problem collected."""

from __future__ import annotations

import os
import re
from typing import Any

from ..core import Diagnostic, TnnError
from ..ir import (
    Boundary,
    Fluid,
    Input,
    LearnFunction,
    LearnInput,
    LearnTarget,
    Link,
    Network,
    Num,
    Param,
    Peltier,
    Radiation,
    Ref,
    Sensor,
    Source,
    Span,
    Temp,
    ThermalNode,
    map_children,
)
from .sources import (
    MAX_FILE_BYTES,
    MAX_FILES,
    MAX_TOTAL_BYTES,
    SourceReadError,
    _decode,
    _statements,
    inside_roots,
    read_source_bytes,
)
from .statements import _Q, _Clause, _Free, _Per, _St
from .units import TEMPERATURE_UNITS, UnitError, dim_eq, format_dim, parse_quantity, unit_scale

MAX_INCLUDE_DEPTH = 32


MAX_SUBNET_DEPTH = 16


_T_NUM = re.compile(r"^T(\d+)$")


class _Scope:
    """Name resolution while expanding subnets. The top scope maps every name to itself; an instance
    scope maps the names declared in the subnet body to ``<inst>.<name>``, the subnet parameters to
    their argument expressions, and everything else through the enclosing scope."""

    def __init__(self, prefix: str = "", local: set[str] | None = None, subst: dict | None = None,
                 parent: "_Scope | None" = None, chain: tuple[str, ...] = ()):
        self.prefix = prefix
        self.local = local or set()
        self.subst = subst or {}
        self.parent = parent
        self.chain = chain

    def decl(self, name: str | None) -> str | None:
        return None if name is None else self.prefix + name

    def name(self, name: str) -> str:
        """A referenced element/param name (dotted `pe.seebeck` resolves through its head)."""
        if self.parent is None:
            return name
        if name in self.local:
            return self.prefix + name
        head = name.split(".", 1)[0]
        if head in self.local:
            return self.prefix + name
        m = _T_NUM.match(name)
        if m and m.group(1) in self.local:
            return self.prefix + m.group(1)  # `T3` of a local node 3: that node (learn arguments)
        return self.parent.name(name)

    def node(self, name: str) -> str:
        if self.parent is None or name in self.subst:
            return name if self.parent is None else self._subst_node(name)
        if name in self.local or name.split(".", 1)[0] in self.local:
            return self.prefix + name
        return self.parent.node(name)

    def _subst_node(self, name: str) -> str:
        e = self.subst[name]
        if isinstance(e, Ref):
            return e.name
        if isinstance(e, Temp):
            return e.node
        return name

    def expr(self, e):
        """Rename the names of an expression for this scope."""
        if self.parent is None:
            return e
        if isinstance(e, Ref):
            if e.name in self.subst:
                return self.subst[e.name]
            m = _T_NUM.match(e.name)
            if m and m.group(1) in self.local and e.name not in self.local:
                return Temp(node=self.prefix + m.group(1), span=e.span)
            if e.name in self.local or e.name.split(".", 1)[0] in self.local:
                return e.model_copy(update={"name": self.prefix + e.name})
            return self.parent.expr(e)
        if isinstance(e, Temp):
            return e.model_copy(update={"node": self.node(e.node)})
        return map_children(e, self.expr)


def _declared_names(body: list[_St]) -> set[str]:
    out: set[str] = set()
    for st in body:
        d = st.data
        if st.kind in ("param", "sensor", "peltier", "fluid"):
            out.add(d["name"])
        elif st.kind in ("node", "boundary"):
            out.add(d["name"])
        elif st.kind == "use":
            out.add(d["inst"])
        for c in st.clauses:
            if c.tag == "as":
                out.add(c.value)
    return out


_ROLE_OF_KEY = {
    "lag": "time_constant", "offset": "offset", "area": "component", "emissivity": "component",
    "view_factor": "component", "current": "component", "seebeck": "component", "resistance": "component",
    "R_internal": "resistance", "inlet": "temperature", "mdot": "component", "cp": "component", "UA": "component",
}


_LEARN_KINDS = ("const", "linear", "poly", "mlp", "table")


_ACTIVATIONS = ("sigmoid", "tanh", "relu", "softplus", "silu")


_LEARN_OPTIONS = {
    "const": ("frozen", "init_from", "replace"),
    "linear": ("frozen", "init_from", "replace"),
    "poly": ("degree", "frozen", "init_from", "replace"),
    "mlp": ("hidden", "activation", "frozen", "init_from", "replace"),
    "table": ("knots", "frozen", "init_from", "replace"),
}


DEFAULT_HIDDEN = [8, 8]


DEFAULT_DEGREE = 2


class _Builder:
    def __init__(self, sources: dict[str, str], roots: tuple[str, ...] = ()):
        self.sources = sources
        self.roots = roots  # the directories includes may come from (real paths)
        self.included: set[str] = set()  # real paths of the files already read (each is read once)
        self.bytes_read = sum(len(t) for t in sources.values())
        self.diags: list[Diagnostic] = []
        self.name: str | None = None
        self.label: str | None = None
        self.temperature_unit = "degC"
        self.files: list[str] = []
        self.params: list[Param] = []
        self.inputs: list[Input] = []
        self.nodes: list[ThermalNode] = []
        self.boundaries: list[Boundary] = []
        self.links: list[Link] = []
        self.radiations: list[Radiation] = []
        self.peltiers: list[Peltier] = []
        self.fluids: list[Fluid] = []
        self.sources_: list[Source] = []
        self.sensors: list[Sensor] = []
        self.learn_stmts: list[tuple[_St, _Scope]] = []
        self.subnets: dict[str, _St] = {}
        self.auto_counts: dict[str, int] = {}

    # -- helpers --------------------------------------------------------------------------

    def err(self, msg: str, span: Span | None, hint: str | None = None, related=()):
        self.diags.append(Diagnostic(msg, span, hint=hint, related=tuple(related)))

    def auto(self, base: str) -> str:
        n = self.auto_counts.get(base, 0) + 1
        self.auto_counts[base] = n
        return base if n == 1 else f"{base}_{n}"

    def temp_literal(self, e):
        """A bare number in a temperature slot is in the file's temperature unit."""
        if isinstance(e, Num) and e.unit is None and not e.dim:
            scale, offset = unit_scale(self.temperature_unit)
            return e.model_copy(update={"value": e.value * scale + offset, "dim": {"K": 1.0},
                                        "unit": self.temperature_unit})
        return e

    def bound(self, q: _Q, value_unit: str | None, temp_slot: bool) -> tuple[float, dict] | None:
        unit = q.unit
        if unit is None:
            unit = value_unit if value_unit is not None else (self.temperature_unit if temp_slot else None)
        try:
            return parse_quantity(q.number, unit)
        except UnitError as err:
            self.err(err.message, q.span, err.hint)
            return None

    def slot(self, name: str, expr, role: str, owner: str | None, span: Span, free: _Free | None = None,
             label: str | None = None, temp_slot: bool = False, per: _Per | None = None) -> str:
        if temp_slot:
            expr = self.temp_literal(expr)
        if per is not None and free is None and isinstance(expr, Num):
            # a derived value is left to the validation pass, which says it cannot be per experiment at all
            self.err("a per-experiment value must be free: write `free per experiment`", per.span,
                     hint="only a fitted constant takes its own value in each data file")
            per = None
        lower = upper = None
        if free is not None and (free.lo is not None or free.hi is not None):
            vunit = expr.unit if isinstance(expr, Num) else None
            vdim = expr.dim if isinstance(expr, Num) else None
            for which, q in (("lower", free.lo), ("upper", free.hi)):
                res = self.bound(q, vunit, temp_slot)
                if res is None:
                    continue
                val, dim = res
                if vdim is not None and (q.unit is not None) and not dim_eq(dim, vdim):
                    self.err(f"the {which} bound `{q.text}` is in `{format_dim(dim)}` but the value is in "
                             f"`{format_dim(vdim)}`", q.span, hint="bounds use the unit of the value")
                if which == "lower":
                    lower = val
                else:
                    upper = val
        p = Param(name=name, expr=expr, dim=expr.dim if isinstance(expr, Num) else {},
                  unit=expr.unit if isinstance(expr, Num) else None, role=role, free=free is not None,
                  lower=lower, upper=upper, per_experiment=per is not None, owner=owner, label=label, span=span)
        self.params.append(p)
        return name

    @staticmethod
    def label_of(st: _St) -> str | None:
        labs = [c.value for c in st.clauses if c.tag == "label"]
        return labs[0] if labs else None

    def single(self, st: _St, tag: str) -> _Clause | None:
        cs = [c for c in st.clauses if c.tag == tag]
        if len(cs) > 1:
            self.err(f"`{tag}` is given twice in this {st.kind}", cs[1].span,
                     related=[("first given here", cs[0].span)])
        return cs[0] if cs else None

    # -- files ----------------------------------------------------------------------------

    def run_file(self, stmts: list[_St], filename: str, scope: _Scope, main: bool, include_chain: tuple[str, ...]):
        self.files.append(filename)
        if main:
            # `network` and `units` apply to the whole file wherever they are written
            nets = [s for s in stmts if s.kind == "network"]
            if not nets:
                first = stmts[0].span if stmts else Span(file=filename, line=1, col=1, end_line=1, end_col=1)
                self.err("missing `network NAME` at the top of the file" if stmts else "the file is empty",
                         Span(file=filename, line=1, col=1, end_line=1, end_col=1) if not stmts else first,
                         hint='a network file starts with `network NAME "label"`')
            else:
                self.name = nets[0].data["name"]
                self.label = nets[0].data["label"]
                for extra in nets[1:]:
                    self.err("`network` is given twice", extra.span, related=[("first given here", nets[0].span)])
            units = [s for s in stmts if s.kind == "units"]
            for u in units[:1]:
                unit = u.data["unit"]
                canon = {"degC": "degC", "K": "K", "degF": "degF", "celsius": "degC", "kelvin": "K",
                         "fahrenheit": "degF"}.get(unit)
                if canon is None:
                    self.err(f"unknown temperature unit `{unit}`", u.data["unit_span"],
                             hint="write `units temperature = degC`, `K` or `degF`")
                else:
                    self.temperature_unit = canon
            for extra in units[1:]:
                self.err("`units` is given twice", extra.span, related=[("first given here", units[0].span)])
        for st in stmts:
            if st.kind in ("network", "units"):
                if not main:
                    self.err(f"`{st.kind}` in an included file", st.span,
                             hint="only the main file names the network and its temperature unit")
                continue
            self.statement(st, scope, include_chain)

    def include(self, st: _St, scope: _Scope, chain: tuple[str, ...]):
        """Read and run an included file once: confined to the include roots, a regular file, size-capped.
        A file already included (a diamond: two files include the same parts) is not read again; its
        declarations are already in the network."""
        rel = st.data["path"]
        base = os.path.dirname(st.file) if os.path.exists(st.file) else ""
        shown = os.path.normpath(os.path.join(base, rel))
        key = os.path.realpath(shown)
        if key in chain:
            names = " -> ".join(os.path.basename(c) for c in (*chain, key))
            self.err(f"include cycle: {names}", st.span, hint="a file cannot include itself, even indirectly")
            return
        if key in self.included:
            return
        if len(chain) > MAX_INCLUDE_DEPTH:
            self.err("includes nested too deeply", st.span)
            return
        if self.roots and not inside_roots(key, self.roots):
            where = self.roots[0] if len(self.roots) == 1 else ", ".join(self.roots)
            self.err(f"the included file `{rel}` is outside the network's directory ({where})", st.span,
                     hint="includes are confined to the main file's directory tree; to allow another directory "
                          "pass `--include-path DIR` (or load(..., include_path=[DIR]))")
            return
        if len(self.included) + 1 >= MAX_FILES:
            self.err(f"the network reads more than {MAX_FILES} files", st.span, hint="join parts into fewer files")
            return
        limit = min(MAX_FILE_BYTES, MAX_TOTAL_BYTES - self.bytes_read)
        try:
            data = read_source_bytes(key, limit=max(limit, 0))
        except SourceReadError as e:
            reason = e.reason
            if limit < MAX_FILE_BYTES and "more than" in reason:
                reason = f"the network's files together are more than {MAX_TOTAL_BYTES:,} bytes"
            self.err(f"cannot read the included file `{rel}`: {reason}", st.span,
                     hint=e.hint or "include paths are relative to the including file")
            return
        self.included.add(key)
        self.bytes_read += len(data)
        try:
            text = _decode(data, shown)
            stmts = _statements(text, shown, self.sources)
        except TnnError as e:
            self.diags.extend(e.diagnostics)
            return
        self.run_file(stmts, shown, scope, main=False, include_chain=(*chain, key))

    # -- statements -----------------------------------------------------------------------

    def statement(self, st: _St, scope: _Scope, chain: tuple[str, ...]):
        getattr(self, "st_" + st.kind)(st, scope, chain)

    def st_include(self, st, scope, chain):
        if scope.parent is not None:
            self.err("`include` inside a subnet", st.span, hint="include files at the top level")
            return
        self.include(st, scope, chain)

    def st_input(self, st, scope, chain):
        d = st.data
        if scope.parent is not None:
            self.err("`input` inside a subnet", st.span,
                     hint="inputs belong to the network; declare them at the top level and use them inside")
            return
        kind, unit, uspan = d["type"]
        col = self.single(st, "column")
        lab = self.label_of(st)
        if kind == "temperature":
            inp = Input(name=d["name"], dim={"K": 1.0}, unit=self.temperature_unit, is_temperature=True,
                        column=col.value if col else d["name"], label=lab, span=st.span)
        else:
            try:
                _, dim = parse_quantity(1.0, unit if unit not in ("", "1") else None)
            except UnitError as e:
                self.err(e.message, uspan, e.hint)
                dim = {}
            is_t = unit in TEMPERATURE_UNITS
            inp = Input(name=d["name"], dim=dim, unit=unit or "1", is_temperature=is_t,
                        column=col.value if col else d["name"], label=lab, span=st.span)
        self.inputs.append(inp)

    def st_param(self, st, scope, chain):
        d = st.data
        self.slot(scope.decl(d["name"]), scope.expr(d["expr"]), "generic", None, st.span, d["free"],
                  self.label_of(st), per=d["per"])

    def st_node(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        p = self.slot(scope.decl(_slot_name("C", d["name"])), scope.expr(d["expr"]), "capacitance", f"node {name}",
                      st.span, d["free"], per=d["per"])
        self.nodes.append(ThermalNode(name=name, capacitance=p, label=self.label_of(st), span=st.span))

    def st_boundary(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        p = self.slot(scope.decl(_slot_name("T", d["name"])), scope.expr(d["expr"]), "temperature",
                      f"boundary {name}", st.span, temp_slot=True)
        self.boundaries.append(Boundary(name=name, temperature=p, label=self.label_of(st), span=st.span))

    def st_link(self, st, scope, chain):
        d = st.data
        a, b = scope.node(d["a"][0]), scope.node(d["b"][0])
        as_ = self.single(st, "as")
        form = d["form"]
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"{form}_{d['a'][0]}_{d['b'][0]}"))
        role = "resistance" if form == "R" else "conductance"
        self.slot(name, scope.expr(d["expr"]), role, f"link {name}", st.span, d["free"], per=d["per"])
        self.links.append(Link(name=name, a=a, b=b, form=form, value=name, label=self.label_of(st), span=st.span))

    def st_source(self, st, scope, chain):
        d = st.data
        node = scope.node(d["node"][0])
        as_ = self.single(st, "as")
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"Q_src_{d['node'][0]}"))
        self.slot(name, scope.expr(d["expr"]), "heat_flow", f"source {name}", st.span, label=self.label_of(st))
        self.sources_.append(Source(name=name, node=node, value=name, span=st.span))

    def st_sensor(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        node = scope.node(d["node"][0])
        lag = self.single(st, "lag")
        off = self.single(st, "offset")
        col = self.single(st, "column")
        lag_p = off_p = None
        if lag is not None:
            lag_p = self.slot(f"{name}.lag", scope.expr(lag.value), "time_constant", f"sensor {name}", lag.span,
                              lag.free, per=lag.per)
        if off is not None:
            off_p = self.slot(f"{name}.offset", scope.expr(off.value), "offset", f"sensor {name}", off.span, off.free,
                              per=off.per)
        self.sensors.append(Sensor(name=name, node=node, column=col.value if col else name, lag=lag_p, offset=off_p,
                                   label=self.label_of(st), span=st.span))

    def _component(self, st, scope, cname, keys, required, owner):
        out = {}
        for key in keys:
            c = self.single(st, key)
            if c is None:
                if key in required:
                    self.err(f"{owner} needs `{key} = ...`", st.span, hint=f"add `{key} = VALUE` to the statement")
                out[key] = None
                continue
            out[key] = self.slot(f"{cname}.{key}", scope.expr(c.value), _ROLE_OF_KEY[key], owner, c.span, c.free,
                                 temp_slot=key == "inlet", per=c.per)
        return out

    def st_radiation(self, st, scope, chain):
        d = st.data
        a, b = scope.node(d["a"][0]), scope.node(d["b"][0])
        as_ = self.single(st, "as")
        name = scope.decl(as_.value if as_ else None) or self.auto(scope.decl(f"rad_{d['a'][0]}_{d['b'][0]}"))
        owner = f"radiation {name}"
        out = self._component(st, scope, name, ("area", "emissivity", "view_factor"), ("area", "emissivity"), owner)
        if out["view_factor"] is None:
            out["view_factor"] = self.slot(f"{name}.view_factor", Num(value=1.0, span=st.span), "component", owner,
                                           st.span)
        self.radiations.append(Radiation(name=name, a=a, b=b, area=out["area"] or f"{name}.area",
                                         emissivity=out["emissivity"] or f"{name}.emissivity",
                                         view_factor=out["view_factor"], span=st.span))

    def st_peltier(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        owner = f"peltier {name}"
        hot, cold = self.single(st, "hot"), self.single(st, "cold")
        for key, c in (("hot", hot), ("cold", cold)):
            if c is None:
                self.err(f"{owner} needs `{key} = NODE`", st.span, hint=f"add `{key} = NODE` to the statement")
        out = self._component(st, scope, name, ("current", "seebeck", "resistance", "R_internal"),
                              ("current", "seebeck", "resistance"), owner)
        self.peltiers.append(Peltier(
            name=name, hot=scope.node(hot.value[0]) if hot else "?", cold=scope.node(cold.value[0]) if cold else "?",
            current=out["current"] or f"{name}.current", seebeck=out["seebeck"] or f"{name}.seebeck",
            resistance=out["resistance"] or f"{name}.resistance", r_internal=out["R_internal"], span=st.span))

    def st_fluid(self, st, scope, chain):
        d = st.data
        name = scope.decl(d["name"])
        owner = f"fluid {name}"
        out = self._component(st, scope, name, ("inlet", "mdot", "cp", "UA"), ("inlet", "mdot", "cp", "UA"), owner)
        self.fluids.append(Fluid(name=name, node=scope.node(d["node"][0]), inlet=out["inlet"] or f"{name}.inlet",
                                 mdot=out["mdot"] or f"{name}.mdot", cp=out["cp"] or f"{name}.cp",
                                 ua=out["UA"] or f"{name}.UA", span=st.span))

    def st_learn(self, st, scope, chain):
        self.learn_stmts.append((st, scope))

    def st_subnet(self, st, scope, chain):
        name = st.data["name"]
        if scope.parent is not None:
            self.err("a `subnet` cannot be defined inside another subnet", st.span,
                     hint="define subnets at the top level; `use` may appear inside a subnet")
            return
        if name in self.subnets:
            self.err(f"subnet `{name}` is defined twice", st.data["name_span"],
                     related=[("first defined here", self.subnets[name].data["name_span"])])
            return
        for sub in st.data["body"]:
            if sub.kind in ("network", "units", "include", "input"):
                self.err(f"`{sub.kind}` inside a subnet", sub.span,
                         hint="a subnet holds nodes, boundaries, links, components, sources, sensors, params, learn "
                              "and use")
        seen: dict[str, Span] = {}
        for p, pspan in st.data["params"]:
            if p in seen:
                self.err(f"subnet parameter `{p}` is listed twice", pspan, related=[("first listed here", seen[p])])
            seen[p] = pspan
        self.subnets[name] = st

    def st_use(self, st, scope, chain):
        d = st.data
        sub = self.subnets.get(d["subnet"])
        if sub is None:
            known = ", ".join(sorted(self.subnets)) or "none defined"
            self.err(f"unknown subnet `{d['subnet']}`", d["subnet_span"],
                     hint=f"subnets must be defined before they are used (known: {known})")
            return
        if d["subnet"] in scope.chain:
            self.err(f"subnet `{d['subnet']}` uses itself", st.span, hint="subnets cannot be recursive")
            return
        if len(scope.chain) >= MAX_SUBNET_DEPTH:
            self.err("subnets nested too deeply", st.span)
            return
        params = {p for p, _ in sub.data["params"]}
        subst = {}
        for _tag, pname, expr, aspan in d["args"]:
            if pname not in params:
                listed = ", ".join(p for p, _ in sub.data["params"]) or "none"
                self.err(f"subnet `{d['subnet']}` has no parameter `{pname}`", aspan, hint=f"its parameters: {listed}")
                continue
            if pname in subst:
                self.err(f"argument `{pname}` is given twice", aspan)
                continue
            subst[pname] = scope.expr(expr)
        missing = [p for p, _ in sub.data["params"] if p not in subst]
        if missing:
            self.err(f"`use {d['subnet']}` is missing the argument{'s' if len(missing) > 1 else ''} "
                     f"{', '.join('`' + m + '`' for m in missing)}", st.span,
                     hint="give every subnet parameter: `use NAME(P = VALUE, ...) as INSTANCE`")
            return
        inst = scope.decl(d["inst"])
        body = [b for b in sub.data["body"] if b.kind not in ("network", "units", "include", "input")]
        local = _declared_names(body)
        inner = _Scope(prefix=inst + ".", local=local, subst=subst, parent=scope, chain=(*scope.chain, d["subnet"]))
        for b in body:
            self.statement(b, inner, chain)

    # -- learn (after everything is declared) ---------------------------------------------

    def build_learned(self) -> list[LearnFunction]:
        taken = {p.name.split(".")[0] for p in self.params} | {x.name for x in self.inputs}
        taken |= {x.name for x in (*self.nodes, *self.boundaries, *self.links, *self.radiations, *self.peltiers,
                                   *self.fluids, *self.sources_, *self.sensors)}
        node_names = {n.name for n in self.nodes} | {b.name for b in self.boundaries}
        out = []
        for st, scope in self.learn_stmts:
            fname = _function_name(st.data["targets"], taken)
            taken.add(fname)
            out.append(self.learn(st, scope, fname, node_names))
        return [f for f in out if f is not None]

    def learn(self, st: _St, scope: _Scope, fname: str, node_names: set[str]) -> LearnFunction | None:
        d = st.data
        kind = d["kind"]
        if kind not in _LEARN_KINDS:
            self.err(f"unknown learned-function kind `{kind}`", d["kind_span"],
                     hint="kinds are const, linear, poly, mlp and table")
            return None
        targets = []
        for tkind, tname, tspan in d["targets"]:
            if tkind == "load":
                targets.append(LearnTarget(kind="heat_load", name=scope.node(tname), span=tspan))
                continue
            resolved = scope.name(tname)
            if resolved.rsplit(".", 1)[-1] in ("Q_hot", "Q_cold", "Q") and "." in resolved:
                targets.append(LearnTarget(kind="flow", name=resolved, span=tspan))
            else:
                targets.append(LearnTarget(kind="param", name=resolved, span=tspan))
        inputs = []
        for ikind, iname, ispan in d["inputs"]:
            if ikind == "node":
                inputs.append(LearnInput(kind="node", name=scope.node(iname), span=ispan))
                continue
            if iname in scope.subst:
                e = scope.subst[iname]
                if isinstance(e, Ref):
                    inputs.append(LearnInput(name=e.name, span=ispan))
                elif isinstance(e, Temp):
                    inputs.append(LearnInput(kind="node", name=e.node, span=ispan))
                else:
                    self.err(f"learned-function argument `{iname}` is an expression here", ispan,
                             hint="arguments must be names of nodes, inputs or parameters")
                continue
            resolved = scope.name(iname)
            inputs.append(LearnInput(name=resolved, span=ispan))
        opts: dict[str, Any] = {}
        allowed = _LEARN_OPTIONS[kind]
        for _tag, oname, oval, ospan in d["opts"]:
            if oname not in ("hidden", "activation", "degree", "knots", "frozen", "init_from", "replace"):
                self.err(f"unknown option `{oname}` for `{kind}`", ospan,
                         hint="options of `" + kind + "`: " + ", ".join(allowed))
                continue
            if oname not in allowed:
                self.err(f"`{oname}` is not an option of `{kind}`", ospan,
                         hint="options of `" + kind + "`: " + ", ".join(allowed))
                continue
            if oname in opts:
                self.err(f"option `{oname}` is given twice", ospan)
                continue
            opts[oname] = (oval, ospan)
        fn: dict[str, Any] = {"name": fname, "kind": kind, "targets": targets, "inputs": inputs, "span": st.span}
        for flag in ("frozen", "replace"):
            if flag in opts:
                val, ospan = opts[flag]
                if val is not None:
                    self.err(f"`{flag}` is a flag: write it without a value", ospan)
                fn[flag] = True
        if "init_from" in opts:
            val, ospan = opts["init_from"]
            if not (isinstance(val, tuple) and val[0] == "string"):
                self.err("`init_from` takes a quoted model directory", ospan, hint='write `init_from = "models/m4"`')
            else:
                base = os.path.dirname(os.path.abspath(st.file)) if os.path.exists(st.file) else os.getcwd()
                fn["init_from"] = os.path.normpath(os.path.join(base, val[1]))
                if self.roots and not inside_roots(os.path.realpath(fn["init_from"]), self.roots):
                    self.err(f"`init_from` names `{val[1]}`, outside the network's directory ({self.roots[0]})",
                             ospan, hint="model directories a network loads are confined like includes; pass "
                                         "`--include-path DIR` to allow another directory")
        if kind == "mlp":
            hidden = list(DEFAULT_HIDDEN)
            if "hidden" in opts:
                val, ospan = opts["hidden"]
                sizes = self._ints(val, ospan, "hidden", allow_scalar=True)
                if sizes is not None:
                    hidden = sizes
            fn["hidden"] = hidden
            if "activation" in opts:
                val, ospan = opts["activation"]
                if not (isinstance(val, tuple) and val[0] == "name" and val[1] in _ACTIVATIONS):
                    self.err("unknown activation", ospan, hint="activations: " + ", ".join(_ACTIVATIONS))
                else:
                    fn["activation"] = val[1]
        if kind == "poly":
            deg = DEFAULT_DEGREE
            if "degree" in opts:
                val, ospan = opts["degree"]
                v = self._ints(val, ospan, "degree", allow_scalar=True, scalar_only=True)
                if v is not None:
                    deg = v[0]
            fn["degree"] = deg
        if kind == "const" and inputs:
            self.err("`const` takes no arguments", st.span, hint="write `learn TARGET as const`")
        if kind in ("linear", "poly", "mlp") and not inputs:
            self.err(f"`{kind}` needs at least one argument", d["kind_span"],
                     hint=f"write `as {kind}(hx1, u1)` with the nodes, inputs or parameters it depends on")
        if kind == "table":
            if len(inputs) != 1:
                self.err("a learned `table` has exactly one argument", d["kind_span"],
                         hint="write `as table(T(hx1); knots = [0 degC, 25 degC, 50 degC])`")
            if "knots" not in opts:
                self.err("a learned `table` needs `knots = [...]`", d["kind_span"],
                         hint="write `as table(x; knots = [0 degC, 25 degC, 50 degC])`")
            else:
                val, ospan = opts["knots"]
                is_node = bool(inputs) and (inputs[0].kind == "node" or inputs[0].name in node_names)
                fn["knots"] = self._knots(val, ospan, is_node)
        return LearnFunction(**fn)

    def _ints(self, val, span, what, allow_scalar=False, scalar_only=False):
        items = None
        if isinstance(val, tuple) and val[0] == "list" and not scalar_only:
            items = val[1]
        elif isinstance(val, _Q) and allow_scalar:
            items = [val]
        if items is None:
            self.err(f"`{what}` takes {'a whole number' if scalar_only else 'a list of layer sizes'}", span,
                     hint="e.g. `degree = 2`" if scalar_only else "e.g. `hidden = [8, 8]`")
            return None
        out = []
        for q in items:
            if (q.unit is not None or not float(q.number).is_integer() or q.number < (0 if scalar_only else 1)
                    or q.number > 100000):
                self.err(f"`{what}` must be {'a whole number' if scalar_only else 'whole numbers of at least 1'}, "
                         f"got `{q.text}`", q.span)
                return None
            out.append(int(q.number))
        if not out and not scalar_only:
            self.err(f"`{what}` is empty", span, hint="e.g. `hidden = [8, 8]`")
            return None
        return out

    def _knots(self, val, span, temp):
        if not (isinstance(val, tuple) and val[0] == "list"):
            self.err("`knots` takes a list of values", span, hint="e.g. `knots = [0 degC, 25 degC, 50 degC]`")
            return []
        out = []
        for q in val[1]:
            unit = q.unit if q.unit is not None else (self.temperature_unit if temp else None)
            try:
                v, _ = parse_quantity(q.number, unit)
            except UnitError as e:
                self.err(e.message, q.span, e.hint)
                return []
            out.append(v)
        if len(out) < 2:
            self.err("`knots` needs at least two values", span)
        elif any(b <= a for a, b in zip(out, out[1:])):
            self.err("`knots` must be strictly increasing", span)
        return out

    def network(self) -> Network:
        learned = self.build_learned()
        return Network(
            name=self.name or "unnamed", label=self.label, temperature_unit=self.temperature_unit,
            source_files=list(dict.fromkeys(self.files)), params=self.params, inputs=self.inputs, nodes=self.nodes,
            boundaries=self.boundaries, links=self.links, radiations=self.radiations, peltiers=self.peltiers,
            fluids=self.fluids, sources=self.sources_, sensors=self.sensors, learned=learned,
        )


def _slot_name(prefix: str, element: str) -> str:
    """The automatic name of a node's capacity (``prefix`` ``C``) or a boundary's temperature (``T``): ``C_hx1``.
    For a dotted element (``r1.air``, as a subnet instance names it) the prefix goes before its last part,
    ``r1.C_air``: the name the instance gives it, so a flat file that spells out an instance's names (what
    :func:`tnn_dsl.lang.printer.print_thn` writes) reads back with the same parameter names."""
    head, dot, tail = element.rpartition(".")
    return f"{head}.{prefix}_{tail}" if dot else f"{prefix}_{element}"


def _function_name(targets, taken: set[str]) -> str:
    """A learned function's name: ``fn_`` + its first target, dots and brackets folded to ``_``
    (``fn_R_hp1``, ``fn_pe_Q_hot``, ``fn_Q_hx2``); ``_2``, ``_3`` … if that is taken. Stable across
    files that learn the same target (M4's Peltier net and M5's share ``fn_pe_Q_hot``)."""
    first = targets[0][1] if targets else "learned"
    if targets and targets[0][0] == "load":
        first = f"Q_{first}"
    base = "fn_" + re.sub(r"[^A-Za-z0-9_]+", "_", str(first)).strip("_")
    name, k = base, 2
    while name in taken:
        name, k = f"{base}_{k}", k + 1
    return name
