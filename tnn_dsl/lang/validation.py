"""The one validation pass: every problem of a parsed network, collected and raised together.

:func:`validate` takes the network the parser built (names unresolved) and returns it with

* every ``Ref`` resolved (``kind`` = ``param`` | ``input``), a bare node/boundary name or ``T3`` in an
  expression turned into a ``Temp``;
* every derived parameter's ``dim`` inferred;
* every ``LearnInput.kind`` resolved (``node`` | ``input`` | ``param``).

It reports (all at once, sorted by position): undefined and duplicate names (with a note "first
defined here"), dimension mismatches naming both units, non-positive capacities/resistances/
conductances/time constants, bounds that exclude the value, `free` on a derived parameter, `per experiment`
on a derived, a fixed or a learned parameter, the same value checks for an expression of constants evaluated with
the written values (``C = c0 - 8 J/K``; :mod:`.constants`), a division by a constant zero in any expression, a
node's ``C_x`` or a boundary's ``T_x`` taking a declared name, dependency cycles between parameters, elements on missing
nodes, learn targets that do not exist and learn inputs that are neither a node, an input nor a parameter,
and connected groups of nodes with no conduction path to a boundary or a fluid inlet (their steady state is
undefined)."""

from __future__ import annotations

import difflib
import math
import re

from ..core import Diagnostic, TnnError
from ..ir import (
    POSITIVE_ROLES,
    Binary,
    Call,
    LearnFunction,
    LearnInput,
    Network,
    Num,
    Param,
    Ref,
    Span,
    Table,
    Temp,
    Unary,
    map_children,
    walk,
)
from .constants import ConstValues
from .units import describe_dim, dim_div, dim_eq, dim_mul, dim_pow, format_dim, unit_dim

_T_NUM = re.compile(r"^T(\d+)$")

# the dimension each parameter role / component key must have
_ROLE_UNIT = {
    "resistance": "K/W", "conductance": "W/K", "capacitance": "J/K", "temperature": "K", "heat_flow": "W",
    "time_constant": "s", "offset": "K",
}
_COMPONENT_UNIT = {
    "current": "A", "seebeck": "V/K", "resistance": "ohm", "R_internal": "K/W", "inlet": "K", "mdot": "kg/s",
    "cp": "J/(kg*K)", "UA": "W/K", "area": "m^2", "emissivity": "1", "view_factor": "1",
}
_POSITIVE_KEYS = ("mdot", "cp", "UA", "area", "emissivity", "view_factor", "resistance", "R_internal")


def _key(d: Diagnostic):
    s = d.span
    return (0, s.file, s.line, s.col) if s is not None else (1, "", 0, 0)


class _V:
    def __init__(self, net: Network):
        self.net = net
        self.diags: list[Diagnostic] = []
        self.params: dict[str, Param] = {}
        self.inputs = {}
        self.nodes = {}
        self.boundaries = {}
        self.param_dims: dict[str, dict | None] = {}
        self.resolving: list[str] = []
        self.resolved_exprs: dict[str, object] = {}

    def err(self, msg, span, hint=None, related=()):
        self.diags.append(Diagnostic(msg, span, hint=hint, related=tuple(related)))

    def suggest(self, name: str, pool) -> str | None:
        close = difflib.get_close_matches(name, list(pool), n=3, cutoff=0.6)
        return ("did you mean " + " or ".join(f"`{c}`" for c in close) + "?") if close else None

    # -- names ----------------------------------------------------------------------------

    def collect_names(self):
        net = self.net
        first: dict[str, object] = {}
        for n in net.nodes:
            self._unique(first, n.name, n, "node")
        for b in net.boundaries:
            self._unique(first, b.name, b, "node")
        self.nodes = {n.name: n for n in net.nodes}
        self.boundaries = {b.name: b for b in net.boundaries}
        values: dict[str, object] = {}
        dup_owner = set()
        elements: dict[str, object] = {}
        for group, what in ((net.links, "link"), (net.radiations, "radiation"), (net.peltiers, "peltier"),
                            (net.fluids, "fluid"), (net.sources, "source"), (net.sensors, "sensor")):
            for e in group:
                if e.name in elements:
                    prev = elements[e.name]
                    dup_owner.add(e.name)
                    self.err(f"`{e.name}` is defined twice", e.span, related=[("first defined here", prev.span)],
                             hint="give the second one another name (`as NAME`)")
                else:
                    elements[e.name] = e
        dup_nodes = {n for n in first if False}
        for i in net.inputs:
            if i.name in values:
                self.err(f"input `{i.name}` is defined twice", i.span,
                         related=[("first defined here", values[i.name].span)])
            else:
                values[i.name] = i
        self.inputs = {i.name: i for i in net.inputs}
        node_owner_dups = self._dup_node_names
        shadowed: set[int] = set()  # the later of two declarations of a name, reported: left out of `params`
        for p in net.params:
            if p.name in values:
                prev = values[p.name]
                same_owner = isinstance(prev, Param) and prev.owner is not None and prev.owner == p.owner
                owner_name = (p.owner or "").split(" ", 1)[-1]
                if not same_owner and owner_name not in node_owner_dups and owner_name not in dup_owner:
                    implicit = self._implicit_collision(p, prev)
                    shadowed.add(id(implicit if implicit is not None else p))
                    if implicit is None:
                        what = "an input" if not isinstance(prev, Param) else "a parameter"
                        self.err(f"the name `{p.name}` is already {what}", p.span,
                                 related=[("first defined here", prev.span)])
                continue
            values[p.name] = p
        del dup_nodes
        self.params = {p.name: p for p in net.params if id(p) not in shadowed}
        self.elements = elements

    _dup_node_names: set = set()

    def _implicit_collision(self, p: Param, prev) -> Param | None:
        """Report a node's capacity (``C_x``) or a boundary's temperature (``T_x``), named by the element,
        that takes a name the user declared, and return it (the user's declaration keeps the name);
        ``None`` if neither of the two is such a parameter."""
        for implicit, other in ((p, prev), (prev, p)):
            kind, _, el = (implicit.owner or "").partition(" ") if isinstance(implicit, Param) else ("", "", "")
            if kind not in ("node", "boundary"):
                continue
            slot = "temperature" if kind == "boundary" else "capacity"
            what = "an input" if not isinstance(other, Param) else "a parameter"
            decl = "input" if not isinstance(other, Param) else "parameter"
            prefix = "T" if kind == "boundary" else "C"
            self.err(f"{kind} `{el}` names its {slot} parameter `{p.name}`, but `{p.name}` is already {what}",
                     implicit.span, related=[(f"the {decl} `{p.name}` is declared here", other.span)],
                     hint=f"a {kind} `NAME` defines the parameter `{prefix}_NAME`: rename the {decl} "
                          f"(e.g. `{p.name}_in`) or the {kind}")
            return implicit
        return None

    def _unique(self, first, name, el, what):
        if name in first:
            prev = first[name]
            self._dup_node_names = self._dup_node_names | {name}
            self.err(f"node `{name}` is defined twice", el.span, related=[("first defined here", prev.span)])
        else:
            first[name] = el

    def is_node(self, name):
        return name in self.nodes or name in self.boundaries

    # -- expressions ----------------------------------------------------------------------

    def resolve(self, e):
        """Resolve names of an expression tree (returns a new tree)."""
        if isinstance(e, Ref):
            if e.name in self.params:
                return e.model_copy(update={"kind": "param"})
            if e.name in self.inputs:
                return e.model_copy(update={"kind": "input"})
            if self.is_node(e.name):
                return Temp(node=e.name, span=e.span)
            m = _T_NUM.match(e.name)
            if m and self.is_node(m.group(1)):
                return Temp(node=m.group(1), span=e.span)
            hint = self.suggest(e.name, [*self.params, *self.inputs, *self.nodes, *self.boundaries])
            self.err(f"undefined name `{e.name}`", e.span,
                     hint=hint or "declare it with `param`, `input`, `node` or `boundary`")
            return e
        if isinstance(e, Temp):
            if not self.is_node(e.node):
                hint = self.suggest(e.node, [*self.nodes, *self.boundaries])
                self.err(f"`T({e.node})`: there is no node `{e.node}`", e.span, hint=hint)
            return e
        return map_children(e, self.resolve)

    def dim(self, e):
        """Static dimension of a resolved expression; ``None`` after a reported problem."""
        if isinstance(e, Num):
            return e.dim
        if isinstance(e, Temp):
            return {"K": 1.0}
        if isinstance(e, Ref):
            if e.kind == "param":
                return self.param_dim(e.name, e.span)
            if e.kind == "input":
                return self.inputs[e.name].dim
            return None
        if isinstance(e, Unary):
            return self.dim(e.arg)
        if isinstance(e, Binary):
            a, b = self.dim(e.left), self.dim(e.right)
            if a is None or b is None:
                return None
            if e.op in "+-":
                if not dim_eq(a, b):
                    verb = "add" if e.op == "+" else "subtract"
                    self.err(f"cannot {verb} {describe_dim(a)} and {describe_dim(b)}", e.span,
                             hint="both sides of + and - need the same unit dimension")
                    return None
                return a
            if e.op == "*":
                return dim_mul(a, b)
            if e.op == "/":
                return dim_div(a, b)
            if b:
                self.err(f"an exponent must be dimensionless, got {describe_dim(b)}", e.right.span)
                return None
            if not a:
                return {}
            if isinstance(e.right, Num):
                return dim_pow(a, e.right.value)
            if isinstance(e.right, Unary) and isinstance(e.right.arg, Num):
                return dim_pow(a, -e.right.arg.value)
            self.err(f"{describe_dim(a)} raised to a variable power", e.span,
                     hint="only dimensionless values may be raised to a non-constant power")
            return None
        if isinstance(e, Call):
            dims = [self.dim(a) for a in e.args]
            if any(d is None for d in dims):
                return None
            if e.fn in ("exp", "log"):
                if dims[0]:
                    self.err(f"`{e.fn}` needs a dimensionless argument, got {describe_dim(dims[0])}", e.span,
                             hint="divide by a reference value first, e.g. `log(R / 1 K/W)`")
                    return None
                return {}
            if e.fn == "sqrt":
                return dim_pow(dims[0], 0.5)
            for a, d in zip(e.args[1:], dims[1:]):
                if not dim_eq(d, dims[0]):
                    self.err(f"the arguments of `{e.fn}` differ: {describe_dim(dims[0])} and {describe_dim(d)}",
                             a.span, hint=f"all arguments of `{e.fn}` need the same unit dimension")
                    return None
            return dims[0]
        if isinstance(e, Table):
            xd = self.dim(e.x)
            if xd is not None and not dim_eq(xd, e.x_dim):
                self.err(f"the table's variable is {describe_dim(xd)} but its points are in "
                         f"`{format_dim(e.x_dim)}`", e.x.span,
                         hint="the x values of the points need the variable's unit")
            return e.y_dim
        return None

    def param_dim(self, name, span=None):
        if name in self.param_dims:
            return self.param_dims[name]
        if name in self.resolving:
            cyc = self.resolving[self.resolving.index(name):] + [name]
            self.err(f"parameter `{name}` depends on itself: {' -> '.join(cyc)}", self.params[name].span,
                     hint="a derived parameter may use other parameters, inputs and temperatures, but not in a circle")
            for n in cyc:
                self.param_dims[n] = None
            return None
        self.resolving.append(name)
        p = self.params[name]
        expr = self.resolved_exprs.get(name)
        if expr is None:
            expr = self.resolve(p.expr)
            self.resolved_exprs[name] = expr
        d = self.dim(expr)
        self.resolving.pop()
        self.param_dims.setdefault(name, d)
        return self.param_dims[name]

    # -- checks of slots --------------------------------------------------------------------

    def slot_checks(self):
        for p in self.net.params:
            if p.name not in self.params or self.params[p.name] is not p:
                continue
            d = self.param_dim(p.name)
            expected_unit = None
            key = (p.name.rsplit(".", 1)[-1]
                   if "." in p.name and p.owner and not p.owner.startswith(("link", "source")) else None)
            if p.role in _ROLE_UNIT and not (key in _COMPONENT_UNIT and p.owner
                                             and p.owner.startswith(("peltier", "fluid", "radiation"))):
                expected_unit = _ROLE_UNIT[p.role]
            elif key in _COMPONENT_UNIT:
                expected_unit = _COMPONENT_UNIT[key]
            if expected_unit is not None and d is not None:
                want = unit_dim(expected_unit)
                if not dim_eq(d, want):
                    self.err(self._mismatch_message(p, expected_unit, d), (p.expr.span or p.span),
                             hint=self._mismatch_hint(p, d))
            # constants
            if isinstance(p.expr, Num):
                v = p.expr.value
                positive = (p.role in ("resistance", "conductance", "capacitance", "time_constant")
                            or key in _POSITIVE_KEYS)
                if positive and v <= 0:
                    self.err(f"{self._what(p)} must be positive, got {_fmt(p)}", p.expr.span or p.span,
                             hint="a zero or negative value has no physical meaning here")
                if key == "emissivity" and v > 1:
                    self.err(f"{self._what(p)} must be at most 1, got {v:g}", p.expr.span or p.span)
                if p.role == "temperature" and v <= 0 and p.dim.get("K") == 1.0:
                    self.err(f"{self._what(p)} is at or below absolute zero ({v:g} K)", p.expr.span or p.span)
                lo, hi = p.lower, p.upper
                if lo is not None and hi is not None and lo >= hi:
                    self.err(f"the bounds of `{p.name}` are empty: the lower bound is not below the upper one",
                             p.span, hint="write `free in [LOW, HIGH]` with LOW < HIGH")
                elif (lo is not None and v < lo) or (hi is not None and v > hi):
                    self.err(f"the bounds of `{p.name}` exclude its value {_fmt(p)}", p.span,
                             hint="the starting value must lie within `free in [LOW, HIGH]`")
                if positive and lo is not None and lo < 0:
                    self.err(f"the lower bound of `{p.name}` is negative but {self._what(p)} must be positive",
                             p.span)
            else:
                v = self.consts.value(p.name)
                if v is not None and d is not None and (expected_unit is None or dim_eq(d, unit_dim(expected_unit))):
                    self._evaluated_checks(p, v, key, d, expected_unit)
            if not isinstance(p.expr, Num) and p.free:
                self.err(f"`{p.name}` is an expression and cannot be `free`", p.span,
                         hint="only a constant is fitted; make the constants inside the expression free instead")
            if p.per_experiment and not isinstance(p.expr, Num):
                self.err(f"`{p.name}` is an expression and cannot be `per experiment`", p.span,
                         hint="only a constant takes its own value in each data file; write `free per experiment` "
                              "on a constant inside the expression instead")
            elif p.per_experiment and not p.free:
                self.err("a per-experiment value must be free: write `free per experiment`", p.span,
                         hint="only a fitted constant takes its own value in each data file")

    def _evaluated_checks(self, p: Param, v: float, key, d, expected_unit):
        """The checks of a written value, for the value of an expression of constants (``C = c0 - 8 J/K``)."""
        unit = f" {expected_unit}" if expected_unit not in (None, "1") else "" if expected_unit else " (SI)"
        what = self._what(p)
        got = f"{'it' if what == f'`{p.name}`' else f'`{p.name}`'} evaluates to {v:g}{unit} with the written values"
        span = p.expr.span or p.span
        deps = sorted({e.name for e in walk(self.resolved_exprs.get(p.name, p.expr))
                       if isinstance(e, Ref) and e.kind == "param"})
        uses = (" (it uses " + ", ".join(f"`{n}`" for n in deps) + ")") if deps else ""
        if (p.role in POSITIVE_ROLES or key in _POSITIVE_KEYS) and v <= 0:
            self.err(f"{what} must be positive, but {got}", span,
                     hint=f"a zero or negative value has no physical meaning here; check the expression{uses}")
        if key == "emissivity" and v > 1:
            self.err(f"{what} must be at most 1, but {got}", span, hint=f"check the expression{uses}")
        if p.role == "temperature" and v <= 0 and dim_eq(d, {"K": 1.0}):
            self.err(f"{what} is at or below absolute zero: {got}", span,
                     hint=f"temperatures are evaluated in kelvin; check the expression{uses}")

    def _what(self, p: Param) -> str:
        owner = p.owner or ""
        kind, _, el = owner.partition(" ")
        if kind == "node":
            return f"the capacity of node `{el}`"
        if kind == "link":
            link = next((l for l in self.net.links if l.name == el), None)
            if link is not None:
                return f"{'R' if link.form == 'R' else 'G'} {link.a} -- {link.b}"
        if kind == "sensor" and p.role == "time_constant":
            return f"the lag of sensor `{el}`"
        return f"`{p.name}`"

    def _mismatch_message(self, p, expected_unit, d):
        given = p.expr.unit if isinstance(p.expr, Num) and p.expr.unit else format_dim(d)
        if isinstance(p.expr, Num) and p.expr.unit is None:
            given_txt = "a plain number without unit"
        else:
            given_txt = f"given in {given}"
        what = describe_dim(unit_dim(expected_unit))
        if p.role == "temperature" and p.owner and p.owner.startswith("boundary"):
            return f"boundary `{p.owner.split(' ', 1)[1]}` needs a temperature (K) but was {given_txt}"
        return f"{self._what(p)} is {what} but was {given_txt}"

    def _mismatch_hint(self, p, d):
        if p.role == "resistance" and dim_eq(d, unit_dim("W/K")):
            return "a resistance is in K/W; use `G a -- b = ...` for a conductance"
        if p.role == "conductance" and dim_eq(d, unit_dim("K/W")):
            return "a conductance is in W/K; use `R a -- b = ...` for a resistance"
        if isinstance(p.expr, Num) and p.expr.unit is None:
            return "add the unit after the number, e.g. `40 J/K`"
        return None

    # -- elements -------------------------------------------------------------------------

    def element_checks(self):
        net = self.net

        def need(name, span, what, allow_boundary=True):
            if name in self.nodes or (allow_boundary and name in self.boundaries):
                return True
            if name in self.boundaries and not allow_boundary:
                self.err(f"{what}: `{name}` is a boundary, not a node", span,
                         hint="a boundary's temperature is imposed; heat into it has no effect")
                return False
            hint = self.suggest(name, [*self.nodes, *self.boundaries]) or "declare it with `node` or `boundary`"
            self.err(f"{what}: there is no node `{name}`", span, hint=hint)
            return False

        for l in net.links:
            need(l.a, l.span, f"{l.form} {l.a} -- {l.b}")
            need(l.b, l.span, f"{l.form} {l.a} -- {l.b}")
            if l.a == l.b:
                self.err(f"link `{l.name}` connects node `{l.a}` to itself", l.span)
            elif l.a in self.boundaries and l.b in self.boundaries:
                self.err(f"link `{l.name}` connects two boundaries", l.span,
                         hint="heat between imposed temperatures changes no state; remove it")
        for r in net.radiations:
            need(r.a, r.span, "radiation")
            need(r.b, r.span, "radiation")
            if r.a == r.b:
                self.err(f"radiation `{r.name}` connects node `{r.a}` to itself", r.span)
        for pe in net.peltiers:
            if pe.hot != "?":
                need(pe.hot, pe.span, f"peltier `{pe.name}` hot side", allow_boundary=False)
            if pe.cold != "?":
                need(pe.cold, pe.span, f"peltier `{pe.name}` cold side", allow_boundary=False)
            if pe.hot == pe.cold and pe.hot != "?":
                self.err(f"peltier `{pe.name}` has the same node on both sides", pe.span)
        for f in net.fluids:
            need(f.node, f.span, f"fluid `{f.name}`", allow_boundary=False)
        for s in net.sources:
            need(s.node, s.span, "source", allow_boundary=False)
        for s in net.sensors:
            need(s.node, s.span, f"sensor `{s.name}`")
        if not net.nodes and not self.diags:
            where = Span(file=net.source_files[0], line=1, col=1, end_line=1, end_col=1) if net.source_files else None
            self.err("the network has no nodes", where, hint="declare at least one `node NAME C = ...`")

    def connectivity(self):
        net = self.net
        adj: dict[str, set[str]] = {n: set() for n in (*self.nodes, *self.boundaries)}

        def edge(a, b):
            if a in adj and b in adj:
                adj[a].add(b)
                adj[b].add(a)

        for l in net.links:
            edge(l.a, l.b)
        for r in net.radiations:
            edge(r.a, r.b)
        for pe in net.peltiers:
            if pe.r_internal is not None:
                edge(pe.hot, pe.cold)
        anchored = set(self.boundaries) | {f.node for f in net.fluids}
        seen: set[str] = set()
        for n in net.nodes:
            if n.name in seen or n.name not in self.nodes:
                continue
            comp, stack = [], [n.name]
            seen.add(n.name)
            while stack:
                x = stack.pop()
                comp.append(x)
                for y in adj.get(x, ()):
                    if y not in seen:
                        seen.add(y)
                        stack.append(y)
            if not any(c in anchored for c in comp):
                ordered = [m.name for m in net.nodes if m.name in comp]
                names = ", ".join(f"`{c}`" for c in ordered[:6]) + (" ..." if len(ordered) > 6 else "")
                self.err(f"{'node' if len(ordered) == 1 else 'nodes'} {names} "
                         f"{'has' if len(ordered) == 1 else 'have'} no conduction path to a boundary or a fluid inlet",
                         self.nodes[ordered[0]].span,
                         hint="its steady state is undefined: connect it with `R`/`G` to a boundary "
                              "(e.g. `G x -- amb = 0.1 W/K`)")

    # -- learned functions ----------------------------------------------------------------

    def learned(self) -> list[LearnFunction]:
        out = []
        owners: dict[str, Span] = {}
        flows = {f"{pe.name}.Q_hot" for pe in self.net.peltiers} | {f"{pe.name}.Q_cold" for pe in self.net.peltiers}
        flows |= {f"{f.name}.Q" for f in self.net.fluids}
        for fn in self.net.learned:
            for t in fn.targets:
                key = f"Q[{t.name}]" if t.kind == "heat_load" else t.name
                if key in owners:
                    self.err(f"`{key}` is learned twice", t.span, related=[("first learned here", owners[key])])
                else:
                    owners[key] = t.span
                if t.kind == "param" and t.name not in self.params:
                    hint = self.suggest(t.name, [*self.params, *flows]) or (
                        "targets are parameters (`R_hp1`, `C_hx1`, `pe.seebeck`), `Q[node]` or flows (`pe.Q_hot`)")
                    what = "input" if t.name in self.inputs else None
                    self.err(f"cannot learn `{t.name}`: " + (
                        "it is an input (read from data)" if what else "there is no such parameter"), t.span, hint=hint)
                elif t.kind == "heat_load" and t.name not in self.nodes:
                    self.err(f"cannot learn `Q[{t.name}]`: there is no node `{t.name}`", t.span,
                             hint=self.suggest(t.name, self.nodes))
                elif t.kind == "flow" and t.name not in flows:
                    self.err(f"cannot learn `{t.name}`: there is no such component flow", t.span,
                             hint=("component flows are " + ", ".join(f"`{x}`" for x in sorted(flows))) if flows else
                             "flows belong to `peltier` (`pe.Q_hot`, `pe.Q_cold`) and `fluid` (`f1.Q`) components")
                elif t.kind == "param" and self.params[t.name].per_experiment:
                    self.err(f"cannot learn `{t.name}`: it is `per experiment`", t.span,
                             related=[("declared per experiment here", self.params[t.name].span)],
                             hint="a learned function gives every data file the same function; drop `per experiment` "
                                  "or the `learn` clause")
            inputs = []
            for li in fn.inputs:
                inputs.append(self._learn_input(li))
            if fn.replace and not any(t.kind == "flow" for t in fn.targets):
                self.err("`replace` applies to flow targets (`pe.Q_hot`, `f1.Q`) only", fn.span)
            if fn.frozen and fn.init_from is None:
                self.err(f"learned function `{fn.name}` is `frozen` but has no `init_from`", fn.span,
                         hint='a frozen function keeps its weights: load them with `init_from = "model_dir"`')
            self._size_check(fn)
            out.append(fn.model_copy(update={"inputs": inputs}))
        return out

    def _size_check(self, fn: LearnFunction) -> None:
        """A learned function larger than ``MAX_LEARNED_WEIGHTS`` is an error before anything is allocated."""
        if fn.kind == "poly" and int(fn.degree or 2) > MAX_POLY_DEGREE:
            self.err(f"learned function `{fn.name}`: degree {fn.degree} is above {MAX_POLY_DEGREE}", fn.span,
                     hint="a correction of high degree oscillates between the data; use degree 2 or 3, or `mlp`")
            return
        if fn.kind == "mlp" and len(fn.hidden) > MAX_HIDDEN_LAYERS:
            self.err(f"learned function `{fn.name}` has {len(fn.hidden)} hidden layers, more than "
                     f"{MAX_HIDDEN_LAYERS}", fn.span, hint="one or two hidden layers are enough for a gray-box "
                                                           "correction: `hidden = [8, 8]`")
            return
        n = fn.weight_count()
        if n <= MAX_LEARNED_WEIGHTS:
            return
        what = {"mlp": "reduce `hidden` (the thesis's functions have a few dozen weights; `hidden = [8, 8]` is the "
                       "default)", "poly": "lower `degree` or use fewer arguments"}.get(fn.kind, "use fewer knots")
        self.err(f"learned function `{fn.name}` would have {n:,} weights (about {_bytes(n * BYTES_PER_WEIGHT)} "
                 f"while training); at most {MAX_LEARNED_WEIGHTS:,} are allowed", fn.span, hint=what)

    def _learn_input(self, li: LearnInput) -> LearnInput:
        if li.kind == "node":
            if not self.is_node(li.name):
                self.err(f"learned-function argument `T({li.name})`: there is no node `{li.name}`", li.span,
                         hint=self.suggest(li.name, [*self.nodes, *self.boundaries]))
            return li
        if self.is_node(li.name):
            return li.model_copy(update={"kind": "node"})
        if li.name in self.inputs:
            return li.model_copy(update={"kind": "input"})
        if li.name in self.params:
            return li.model_copy(update={"kind": "param"})
        m = _T_NUM.match(li.name)
        if m and self.is_node(m.group(1)):
            return li.model_copy(update={"kind": "node", "name": m.group(1)})
        hint = self.suggest(li.name, [*self.nodes, *self.boundaries, *self.inputs, *self.params])
        self.err(f"learned-function argument `{li.name}` is neither a node, an input nor a parameter", li.span,
                 hint=hint or "arguments are nodes (`hx1`, `T3`), inputs or parameters")
        return li

    # -- run --------------------------------------------------------------------------------

    def run(self) -> Network:
        self.collect_names()
        for p in self.net.params:
            if p.name in self.params and self.params[p.name] is p:
                self.param_dim(p.name)
        self.consts = ConstValues(self.params, self.resolved_exprs, lambda msg, span, hint: self.err(msg, span, hint))
        self.slot_checks()
        self.element_checks()
        if not self.diags:
            self.connectivity()
        learned = self.learned()
        params = []
        for p in self.net.params:
            expr = self.resolved_exprs.get(p.name, p.expr) if self.params.get(p.name) is p else p.expr
            upd = {"expr": expr}
            d = self.param_dims.get(p.name)
            if not isinstance(p.expr, Num) and d is not None:
                upd["dim"] = d
            params.append(p.model_copy(update=upd))
        return self.net.model_copy(update={"params": params, "learned": learned})


MAX_LEARNED_WEIGHTS = 1_000_000
"""The most weights one learned function may have (gray-box corrections are small; 1e6 float64 weights with
their gradient and Adam's two moments take 32 MB, before the rollout's per-step activations)."""
MAX_POLY_DEGREE = 8
MAX_HIDDEN_LAYERS = 16
BYTES_PER_WEIGHT = 32  # float64 value, gradient and two Adam moments


def _bytes(n: float) -> str:
    for unit in ("B", "kB", "MB", "GB", "TB", "PB"):
        if n < 1000:
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} EB"


PLAUSIBLE_MAGNITUDE = {
    "capacitance": (1e-6, 1e12, "J/K"),     # a milligram of silicon … a large building
    "resistance": (1e-6, 1e9, "K/W"),
    "conductance": (1e-9, 1e6, "W/K"),
    "time_constant": (1e-6, 1e9, "s"),
}
"""Values outside these SI ranges are legal but almost always a typo or a wrong unit: ``magnitude_warnings``."""


def magnitude_warnings(net: Network) -> list[Diagnostic]:
    """Warnings (not errors) for written capacities, resistances, conductances and time constants outside
    :data:`PLAUSIBLE_MAGNITUDE`: ``G = 1e308 W/K`` or ``R = 2e-7 K/W`` pass the checks but make the network stiff
    beyond any explicit step or its steady state overflow. ``tnnc check`` and ``tnnc simulate`` print them."""
    out = []
    for p in net.params:
        rng = PLAUSIBLE_MAGNITUDE.get(p.role)
        v = p.value
        if rng is None or v is None or not math.isfinite(v) or v <= 0:
            continue
        lo, hi, unit = rng
        if lo <= v <= hi:
            continue
        what = p.role.replace("_", " ")
        out.append(Diagnostic(
            f"`{p.name}` is a {what} of {v:g} {unit}, {'below' if v < lo else 'above'} the {lo:g} … {hi:g} {unit} "
            "a lumped thermal network usually has", p.expr.span or p.span, severity="warning",
            hint="check the number and its unit: a value orders of magnitude off makes every explicit step "
                 "unstable or the steady state overflow"))
    return out


def value_problem(p: Param, v: float) -> str | None:
    """What is physically wrong with ``v`` (SI) as the value of constant ``p``, or ``None``: the checks of a
    written number (positive capacities, resistances, conductances, time constants and component values,
    emissivity at most 1, temperatures above absolute zero) for values that were not written (a stored model's,
    a fit's)."""
    if not math.isfinite(v):
        return f"{v} is not a finite number"
    key = p.name.rsplit(".", 1)[-1] if "." in p.name and p.owner and not p.owner.startswith(("link", "source")) \
        else None
    if (p.role in POSITIVE_ROLES or key in _POSITIVE_KEYS) and v <= 0:
        what = (p.role if p.role in POSITIVE_ROLES else key or "value").replace("_", " ")
        return f"a {what} must be positive, got {v:g} (SI)"
    if key == "emissivity" and v > 1:
        return f"an emissivity must be at most 1, got {v:g}"
    if p.role == "temperature" and v <= 0 and p.dim.get("K") == 1.0:
        return f"a temperature must be above absolute zero, got {v:g} K"
    return None


def _fmt(p: Param) -> str:
    if isinstance(p.expr, Num) and p.expr.unit:
        return f"{p.expr.value:g} (SI; written in {p.expr.unit})"
    return f"{p.expr.value:g}" if isinstance(p.expr, Num) else p.name


def validate(net: Network, prior: list[Diagnostic] | None = None) -> Network:
    """Check ``net`` and return it with names resolved. Raises one :class:`TnnError` holding every
    problem (``prior``: problems already found by the parser, reported together, sorted by position)."""
    v = _V(net)
    v._dup_node_names = set()
    out = v.run()
    diags = list(prior or []) + v.diags
    if diags:
        errors = [d for d in diags if d.severity == "error"]
        if errors:
            seen = set()
            uniq = []
            for d in sorted(diags, key=_key):
                k = (d.message, d.span)
                if k not in seen:
                    seen.add(k)
                    uniq.append(d)
            raise TnnError(uniq)
    return out


__all__ = ["validate"]
