"""Emitters: the validated IR written out for people and for other tools.

* :func:`equations` — the ODE system, one line per state, every term visible (links, radiation,
  Peltier, fluids, sources, learned heat loads, sensor-lag states, outputs), followed by the component
  definitions, the learned functions (as functions of their inputs) and the parameter table (SI).
* :func:`ir_json` — the IR as JSON; ``Network.from_json(ir_json(net))`` gives the same IR and
  ``ir_json`` of that is byte-identical (round trip).
* :func:`dot` — a Graphviz DOT picture: thermal nodes, boundaries, fluid inlets, links labelled with
  their values and units, components styled by kind, learned parts highlighted in red.
* :func:`render_png` — DOT → PNG with the ``dot`` binary when installed, else a matplotlib + networkx
  drawing of the same graph.

Nothing here evaluates anything: parameters are written by name, expressions are printed from their
trees. Units are printed in SI (the IR holds SI values; the text the user wrote is kept in
``Param.unit`` for reference).
"""

from __future__ import annotations

import math

from ..core import TnnError
from .network import (
    POSITIVE_ROLES,
    Binary,
    Call,
    Dim,
    Expr,
    LearnFunction,
    Network,
    Num,
    Param,
    Ref,
    Table,
    Temp,
    Unary,
)

__all__ = ["equations", "ir_json", "network_from_json", "dot", "format_dim", "format_quantity", "format_expr",
           "element_label", "LEARNED_COLOR"]

SIGMA = 5.670374419e-8
"""Stefan–Boltzmann constant, W/(m²·K⁴)."""

# ---------------------------------------------------------------------------------------------
# Units and quantities
# ---------------------------------------------------------------------------------------------

_BASE_ORDER = ("kg", "m", "s", "K", "A", "mol", "cd")

# Named SI dimensions, tried before the generic product of base units. Keys are sorted tuples.
_NAMED_DIMS: dict[tuple[tuple[str, float], ...], str] = {}


def _key(d: Dim) -> tuple[tuple[str, float], ...]:
    return tuple(sorted((k, float(v)) for k, v in d.items() if v))


for _text, _dim in [
    ("K/W", {"K": 1, "kg": -1, "m": -2, "s": 3}),
    ("W/K", {"kg": 1, "m": 2, "s": -3, "K": -1}),
    ("J/K", {"kg": 1, "m": 2, "s": -2, "K": -1}),
    ("W", {"kg": 1, "m": 2, "s": -3}),
    ("J", {"kg": 1, "m": 2, "s": -2}),
    ("K", {"K": 1}),
    ("K/s", {"K": 1, "s": -1}),
    ("s", {"s": 1}),
    ("A", {"A": 1}),
    ("V", {"kg": 1, "m": 2, "s": -3, "A": -1}),
    ("V/K", {"kg": 1, "m": 2, "s": -3, "A": -1, "K": -1}),
    ("ohm", {"kg": 1, "m": 2, "s": -3, "A": -2}),
    ("W/A", {"kg": 1, "m": 2, "s": -3, "A": -1}),
    ("kg/s", {"kg": 1, "s": -1}),
    ("J/(kg·K)", {"m": 2, "s": -2, "K": -1}),
    ("W/m²", {"kg": 1, "s": -3}),
    ("W/(m²·K)", {"kg": 1, "s": -3, "K": -1}),
    ("W/(m·K)", {"kg": 1, "m": 1, "s": -3, "K": -1}),
    ("m²", {"m": 2}),
    ("m", {"m": 1}),
    ("kg", {"kg": 1}),
    ("1/K", {"K": -1}),
    ("1/s", {"s": -1}),
]:
    _NAMED_DIMS[_key(_dim)] = _text

_SUPERSCRIPT = str.maketrans("0123456789-.", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻·")


def _pow_text(base: str, exp: float, ascii_only: bool) -> str:
    if exp == 1:
        return base
    e = f"{exp:g}"
    return f"{base}^{e}" if ascii_only else base + e.translate(_SUPERSCRIPT)


def format_dim(dim: Dim | None, *, ascii_only: bool = False) -> str:
    """The SI unit of a dimension: ``{"K": 1, "kg": -1, "m": -2, "s": 3}`` → ``"K/W"``; ``{}`` → ``"1"``."""
    if not dim or not any(dim.values()):
        return "1"
    named = _NAMED_DIMS.get(_key(dim))
    if named is not None:
        return _asciify(named) if ascii_only else named
    num = [(k, v) for k in _BASE_ORDER for kk, v in dim.items() if kk == k and v > 0]
    den = [(k, -v) for k in _BASE_ORDER for kk, v in dim.items() if kk == k and v < 0]
    dot_ = "*" if ascii_only else "·"
    top = dot_.join(_pow_text(k, v, ascii_only) for k, v in num) or "1"
    if not den:
        return top
    bottom = dot_.join(_pow_text(k, v, ascii_only) for k, v in den)
    return f"{top}/({bottom})" if len(den) > 1 else f"{top}/{bottom}"


def _asciify(text: str) -> str:
    text = (
        text.replace("·", "*").replace("²", "^2").replace("³", "^3").replace("⁴", "^4").replace("−", "-")
        .replace("½", "0.5").replace("σ", "sigma").replace("⁻", "^-").replace("≥", ">=").replace("≤", "<=")
        .replace("→", "->").replace("—", "--").replace("×", "x").replace("°", "deg").replace("≈", "~")
        .replace("≳", ">~").replace("≲", "<~").replace("–", "-").replace("T̄", "Tmean")
    )
    if not text.isascii():  # user labels: fold accents, then mark what is left
        import unicodedata

        text = unicodedata.normalize("NFKD", text).encode("ascii", "replace").decode("ascii")
    return text


def _fmt_number(x: float) -> str:
    if x == 0:
        return "0"
    if math.isinf(x) or math.isnan(x):
        return str(x)
    text = f"{x:.6g}"
    if "e" in text:
        mant, exp = text.split("e")
        return f"{mant}e{int(exp)}"
    return text


def format_quantity(value: float, dim: Dim | None, *, ascii_only: bool = False) -> str:
    """``0.2, K/W`` → ``"0.2 K/W"``; dimensionless values print bare."""
    unit = format_dim(dim, ascii_only=ascii_only)
    return _fmt_number(value) if unit == "1" else f"{_fmt_number(value)} {unit}"


# ---------------------------------------------------------------------------------------------
# Symbols and expressions
# ---------------------------------------------------------------------------------------------


def _temp_sym(node: str) -> str:
    """The temperature symbol of a node or boundary: ``T_hx1``; numbered nodes as on a design card: ``T3``."""
    return f"T{node}" if node[:1].isdigit() else f"T_{node}"


def _sensor_sym(sensor: str) -> str:
    """The state of a lagged sensor (the temperature the sensor itself is at): ``Ts_T1``."""
    return f"Ts_{sensor}"


class _Printer:
    """Prints symbols and expressions of one network (knows which parameters are learned)."""

    _PREC = {"+": 1, "-": 1, "*": 2, "/": 2, "neg": 3, "^": 4}

    def __init__(self, net: Network, *, ascii_only: bool = False):
        self.net = net
        self.ascii = ascii_only
        self.params: dict[str, Param] = {p.name: p for p in net.params}
        self.inputs = {i.name: i for i in net.inputs}
        self.targets = net.learned_targets()
        self.boundary_params = {b.temperature for b in net.boundaries}

    # -- small pieces ------------------------------------------------------------------------

    def t(self, text: str) -> str:
        return _asciify(text) if self.ascii else text

    @property
    def mul(self) -> str:
        return "*" if self.ascii else "·"

    @property
    def minus(self) -> str:
        return "-" if self.ascii else "−"

    def args(self, fn: LearnFunction) -> str:
        """The argument list of a learned function as the user wrote it: ``hx1, hp, u1`` (numbered nodes ``T3``)."""
        out = []
        for a in fn.inputs:
            if a.kind == "node" or (a.kind == "unresolved" and self._is_node(a.name)):
                out.append(f"T{a.name}" if a.name[:1].isdigit() else a.name)
            else:
                out.append(a.name)
        return ", ".join(out)

    def call(self, fn: LearnFunction) -> str:
        """``(hx1, hp, u1)`` for a function with inputs, ``""`` for a constant one."""
        return f"({self.args(fn)})" if fn.inputs else ""

    def kind_call(self, fn: LearnFunction) -> str:
        """``linear(hx1, u1)``, or ``const``."""
        return f"{fn.kind}{self.call(fn)}"

    def _is_node(self, name: str) -> bool:
        return any(n.name == name for n in self.net.nodes) or any(b.name == name for b in self.net.boundaries)

    def param(self, name: str, *, inline_alias: bool = True) -> str:
        """A parameter's symbol: its name; ``name(args)`` when a learned function produces it; the input's
        name when the parameter is a bare alias of an input (``pe.current = I`` prints ``I``)."""
        if name in self.targets:
            fn, _ = self.targets[name]
            return f"{name}({self.args(fn)})" if fn.inputs else name
        p = self.params.get(name)
        if inline_alias and p is not None and name not in self.boundary_params:
            e = p.expr
            if isinstance(e, Ref) and (e.kind == "input" or (e.kind == "unresolved" and e.name in self.inputs)):
                return e.name
        return name

    # -- expressions -------------------------------------------------------------------------

    def expr(self, e: Expr, parent: int = 0) -> str:
        if isinstance(e, Num):
            text = format_quantity(e.value, e.dim, ascii_only=self.ascii)
            # a quantity with a unit binds like a product
            return f"({text})" if (" " in text and parent >= 2) or (e.value < 0 and parent >= 1) else text
        if isinstance(e, Ref):
            if e.kind == "param" or (e.kind == "unresolved" and e.name in self.params):
                return self.param(e.name, inline_alias=False)
            return e.name
        if isinstance(e, Temp):
            return _temp_sym(e.node)
        if isinstance(e, Unary):
            inner = self.expr(e.arg, self._PREC["neg"])
            text = f"{self.minus}{inner}"
            return f"({text})" if parent > self._PREC["neg"] else text
        if isinstance(e, Binary):
            prec = self._PREC[e.op]
            if e.op == "^":  # right-associative
                left = self.expr(e.left, prec + 1)
                right = self.expr(e.right, prec)
            else:  # left-associative: the right operand of - and / needs brackets at equal precedence
                left = self.expr(e.left, prec)
                right = self.expr(e.right, prec + 1 if e.op in "-/" else prec)
            op = {"+": " + ", "-": f" {self.minus} ", "*": self.mul, "/": "/", "^": "^"}[e.op]
            text = f"{left}{op}{right}"
            return f"({text})" if prec < parent else text
        if isinstance(e, Call):
            return f"{e.fn}({', '.join(self.expr(a) for a in e.args)})"
        if isinstance(e, Table):
            pts = ", ".join(
                f"{format_quantity(x, e.x_dim, ascii_only=self.ascii)}: "
                f"{format_quantity(y, e.y_dim, ascii_only=self.ascii)}"
                for x, y in zip(e.xs, e.ys)
            )
            return f"table({self.expr(e.x)}; {pts})"
        raise TypeError(f"unknown expression node {type(e).__name__}")  # pragma: no cover - IR is closed


def format_expr(net: Network, e: Expr, *, ascii_only: bool = False) -> str:
    """An expression of ``net`` as text: ``0.2 K/W·(1 + 1.5·(u1 − 0.5))``; learned parameters print as
    functions of their inputs (``R_hp1(hx1, hp, u1)``), node temperatures as ``T_hx1`` (``T3``)."""
    return _Printer(net, ascii_only=ascii_only).expr(e)


# ---------------------------------------------------------------------------------------------
# equations
# ---------------------------------------------------------------------------------------------


def _learned_formula(pr: _Printer, net: Network, fn: LearnFunction, idx: int) -> str:
    """How target ``idx`` of ``fn`` is computed, in words and symbols (the contract in architecture.md)."""
    tgt = fn.targets[idx]
    z = f"z{idx + 1}" if pr.ascii else f"z{_sub(idx + 1)}"
    call = pr.call(fn)
    zcall = f"{z}{call}"
    if tgt.kind == "heat_load":
        node = tgt.name
        return (f"Q[{node}]{call} = y_scale{pr.mul}{zcall}"
                f"   extra heat into {node}, W; 0 W untrained")
    if tgt.kind == "flow":
        comp, _, flow = tgt.name.partition(".")
        if fn.replace:
            return (f"{tgt.name}{call} = y_scale{pr.mul}{zcall}"
                    f"   replaces the physics flow of {comp} (pre-fitted to it), W")
        return (f"{tgt.name}{call} = {tgt.name}_physics + y_scale{pr.mul}{zcall}"
                f"   correction to the physics flow of {comp}, W; = physics untrained")
    p = pr.params.get(tgt.name)
    if p is None:  # pragma: no cover - validation guarantees targets exist
        return f"{tgt.name}{call} = ?"
    nominal = pr.expr(p.expr)
    if p.role in POSITIVE_ROLES:
        return (f"{tgt.name}{call} = {nominal}{pr.mul}pos1(1 + {zcall})"
                f"   positive by construction; = nominal untrained")
    return f"{tgt.name}{call} = {nominal} + y_scale{pr.mul}{zcall}   = nominal untrained"


def _sub(i: int) -> str:
    return str(i).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))


def _fn_signature(pr: _Printer, fn: LearnFunction) -> str:
    opts = []
    if fn.kind == "mlp":
        opts.append(f"hidden = [{', '.join(str(h) for h in fn.hidden)}]")
        opts.append(f"activation = {fn.activation}")
    if fn.kind == "poly" and fn.degree is not None:
        opts.append(f"degree = {fn.degree}")
    if fn.kind == "table" and fn.knots:
        is_temp = bool(fn.inputs) and (fn.inputs[0].kind == "node" or pr._is_node(fn.inputs[0].name))
        opts.append(f"knots = [{', '.join(_fmt_number(k) + (' K' if is_temp else '') for k in fn.knots)}]")
    if fn.replace:
        opts.append("replace")
    inner = pr.args(fn)
    if opts:
        inner = f"{inner}; {', '.join(opts)}" if inner else ", ".join(opts)
    sig = f"{fn.kind}({inner})" if (inner or fn.kind != "const") else "const"
    flags = []
    if fn.frozen:
        flags.append("frozen")
    if fn.init_from:
        flags.append(f"weights from {fn.init_from!r}")
    tail = f"   [{', '.join(flags)}]" if flags else ""
    targets = ", ".join(f"Q[{t.name}]" if t.kind == "heat_load" else t.name for t in fn.targets)
    return f"{fn.name} = {sig} {pr.t('→')} {targets}{tail}"


def _param_line(pr: _Printer, p: Param) -> str:
    if isinstance(p.expr, Num):
        text = f"{p.name} = {format_quantity(p.expr.value, p.expr.dim or p.dim, ascii_only=pr.ascii)}"
        notes = []
        if p.free:
            if p.lower is not None or p.upper is not None:
                lo = "-inf" if p.lower is None else _fmt_number(p.lower)
                hi = "inf" if p.upper is None else _fmt_number(p.upper)
                notes.append(f"free in [{lo}, {hi}] {format_dim(p.dim, ascii_only=pr.ascii)}".rstrip(" 1"))
            else:
                notes.append("free")
        if p.per_experiment:
            notes.append("per experiment")
    else:
        text = f"{p.name} = {pr.expr(p.expr)}"
        unit = format_dim(p.dim, ascii_only=pr.ascii)
        e = p.expr
        is_input = isinstance(e, Ref) and (e.kind == "input" or (e.kind == "unresolved" and e.name in pr.inputs))
        notes = [("input" if is_input else "derived") + (f", {unit}" if unit != "1" else "")]
    if p.name in pr.targets:
        notes.append(f"learned by {pr.targets[p.name][0].name} (this is its nominal)")
    if p.role in POSITIVE_ROLES:
        notes.append("positive")
    if p.label:
        notes.append(f'"{p.label}"')
    return f"{text}   ({'; '.join(notes)})" if notes else text


def equations(net: Network, *, ascii_only: bool = False) -> str:
    """The network's ODE system in readable form (str, ends with a newline).

    One line per state: ``C_<node>·dT_<node>/dt = Σ terms`` (W) for thermal nodes (temperatures K),
    ``<sensor>.lag·d<sensor>/dt = T_<node> − <sensor>`` for lagged sensors; then the outputs (K), the
    component definitions, the learned functions (each target written as a function of the learned
    function's inputs, with how it relates to its nominal value) and the parameter table in SI.
    ``ascii_only=True`` writes ``*``, ``-`` and ``^`` instead of ``·``, ``−`` and superscripts."""
    pr = _Printer(net, ascii_only=ascii_only)
    terms, flows_def = _node_terms(pr, net, ascii_only)
    lines = _equations_header(pr, net, ascii_only) + _state_lines(pr, net, terms)
    lines += _equations_sections(pr, net, flows_def)
    return "\n".join(lines) + "\n"


def _equations_header(pr: _Printer, net: Network, ascii_only: bool) -> list[str]:
    """The comment lines above the equations: name, states, inputs, units."""
    lines: list[str] = []
    head = f"# network {net.name}"
    if net.label:
        head += f" — {net.label}"
    lines.append(pr.t(head))
    lines.append(pr.t(f"# states (K): {', '.join(_temp_sym(n.name) for n in net.nodes) or 'none'}"
                      + "".join(f", {_sensor_sym(s.name)}" for s in net.sensors if s.lag)))
    if net.inputs:
        ins = ", ".join(
            f"{i.name} [{'K' if i.is_temperature else format_dim(i.dim, ascii_only=ascii_only)}]" for i in net.inputs
        )
        lines.append(f"# inputs (SI): {ins}")
    lines.append(pr.t(f"# temperatures in kelvin (the file's unit is {net.temperature_unit}); heat flows in W; "
                      f"σ = {SIGMA:g} W/(m²·K⁴)" if net.radiations else
                      f"# temperatures in kelvin (the file's unit is {net.temperature_unit}); heat flows in W"))
    lines.append("")
    return lines


def _node_terms(pr: _Printer, net: Network, ascii_only: bool) -> tuple[dict[str, list[str]], list[str]]:
    """The heat-flow terms (W) into each thermal node, ``{node: [term]}``, and the component-flow definitions
    (the physics part of flows that a learned function corrects, the fluids' outlet shares)."""
    m, mi = pr.mul, pr.minus
    terms: dict[str, list[str]] = {n.name: [] for n in net.nodes}
    flows_def: list[str] = []

    def add(node: str, term: str) -> None:
        if node in terms:
            terms[node].append(term)

    def diff(a: str, b: str) -> str:
        return f"({_temp_sym(a)} {mi} {_temp_sym(b)})"

    for link in net.links:
        v = pr.param(link.value)
        for me, other in ((link.a, link.b), (link.b, link.a)):
            add(me, f"{diff(other, me)}/{v}" if link.form == "R" else f"{v}{m}{diff(other, me)}")

    for r in net.radiations:
        coef = m.join(pr.param(x) for x in (r.area, r.emissivity, r.view_factor))
        for me, other in ((r.a, r.b), (r.b, r.a)):
            four = "^4" if ascii_only else "⁴"
            add(me, f"{pr.t('σ')}{m}{coef}{m}({_temp_sym(other)}{four} {mi} {_temp_sym(me)}{four})")

    half = "0.5" if ascii_only else "½"
    sq = "^2" if ascii_only else "²"
    for pe in net.peltiers:
        cur, s, rel = pr.param(pe.current), pr.param(pe.seebeck), pr.param(pe.resistance)
        q_hot = f"{s}{m}{_temp_sym(pe.hot)}{m}{cur} + {half}{m}{rel}{m}{cur}{sq}"
        q_cold = f"{mi}{s}{m}{_temp_sym(pe.cold)}{m}{cur} + {half}{m}{rel}{m}{cur}{sq}"
        for flow, node, phys in (("Q_hot", pe.hot, q_hot), ("Q_cold", pe.cold, q_cold)):
            key = f"{pe.name}.{flow}"
            if key in pr.targets:
                fn, _ = pr.targets[key]
                add(node, f"{key}{pr.call(fn)}")
                if not fn.replace:
                    flows_def.append(f"{key}_physics = {phys}   (into {node})")
            else:
                add(node, f"({phys})")
        if pe.r_internal:
            rin = pr.param(pe.r_internal)
            add(pe.hot, f"{diff(pe.cold, pe.hot)}/{rin}")
            add(pe.cold, f"{diff(pe.hot, pe.cold)}/{rin}")

    for f in net.fluids:
        key = f"{f.name}.Q"
        mdot, cp, ua, tin = pr.param(f.mdot), pr.param(f.cp), pr.param(f.ua), pr.param(f.inlet)
        a = f"a_{f.name}"
        phys = f"{mdot}{m}{cp}{m}(1 {mi} {a}){m}({tin} {mi} {_temp_sym(f.node)})"
        flows_def.append(f"{a} = exp({mi}{ua}/({mdot}{m}{cp}))   (fluid {f.name}: share of the inlet-to-node "
                         f"difference left at the outlet)")
        if key in pr.targets:
            fn, _ = pr.targets[key]
            add(f.node, f"{key}{pr.call(fn)}")
            if not fn.replace:
                flows_def.append(f"{key}_physics = {phys}   (into {f.node})")
        else:
            add(f.node, phys)

    for src in net.sources:
        add(src.node, pr.param(src.value))

    for fn in net.learned:
        for t in fn.targets:
            if t.kind == "heat_load":
                add(t.name, f"Q[{t.name}]{pr.call(fn)}")

    return terms, flows_def


def _state_lines(pr: _Printer, net: Network, terms: dict[str, list[str]]) -> list[str]:
    """One line per state: ``C·dT/dt = Σ terms`` per thermal node, then the lag state of each lagged sensor."""
    m, mi = pr.mul, pr.minus
    lines: list[str] = []
    for n in net.nodes:
        c = pr.param(n.capacitance)
        d = f"d{_temp_sym(n.name)}/dt"
        rhs = " + ".join(terms[n.name]) if terms[n.name] else "0"
        rhs = rhs.replace(f" + {mi}", f" {mi} ")
        lab = f"   # {n.label}" if n.label else ""
        lines.append(pr.t(f"{c}{m}{d} = {rhs}{lab}"))

    lagged = [s for s in net.sensors if s.lag]
    for s in lagged:
        lines.append(pr.t(f"{pr.param(s.lag)}{m}d{_sensor_sym(s.name)}/dt = {_temp_sym(s.node)} {mi} "
                          f"{_sensor_sym(s.name)}   # sensor {s.name}: first-order lag state"))

    return lines


def _equations_sections(pr: _Printer, net: Network, flows_def: list[str]) -> list[str]:
    """The sections below the equations: outputs (K), component flows, learned functions, parameters (SI)."""
    lines: list[str] = []
    if net.sensors:
        lines.append("")
        lines.append("outputs (K)")
        for s in net.sensors:
            base = _sensor_sym(s.name) if s.lag else _temp_sym(s.node)
            off = f" + {pr.param(s.offset)}" if s.offset else ""
            lines.append(pr.t(f"  {s.name} = {base}{off}   (column \"{s.column}\")"))

    if flows_def:
        lines.append("")
        lines.append("component flows")
        lines.extend(pr.t(f"  {d}") for d in flows_def)

    if net.learned:
        lines.append("")
        lines.append("learned functions (z = the function's raw output, 0 untrained)")
        for fn in net.learned:
            lines.append(pr.t(f"  {_fn_signature(pr, fn)}"))
            for i in range(len(fn.targets)):
                lines.append(pr.t(f"    {_learned_formula(pr, net, fn, i)}"))
        if any(pr.params.get(t.name) is not None and pr.params[t.name].role in POSITIVE_ROLES
               for fn in net.learned for t in fn.targets if t.kind == "param"):
            lines.append(pr.t("  pos1(v) = softplus(4·v)/softplus(4): positive, pos1(1) = 1, ≈ v for v ≳ 0.5"))

    if net.params:
        lines.append("")
        lines.append("parameters (SI)")
        for p in net.params:
            lines.append(pr.t(f"  {_param_line(pr, p)}"))
    return lines


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------


def ir_json(net: Network, *, indent: int | None = 2) -> str:
    """The IR as JSON text (ends with a newline). ``ir_json(Network.from_json(s)) == s`` for any ``s``
    this function wrote: the round trip is exact (floats are written with their shortest repr)."""
    return net.to_json(indent=indent) + "\n"


def network_from_json(text: str, filename: str = "<json>") -> Network:
    """Read IR JSON (as :func:`ir_json` writes it); a malformed file raises :class:`TnnError`."""
    import pydantic

    try:
        return Network.from_json(text)
    except pydantic.ValidationError as err:
        from ..core import Diagnostic

        diags = []
        for e in err.errors()[:10]:
            loc = ".".join(str(x) for x in e.get("loc", ()))
            diags.append(Diagnostic(f"{filename}: not a tnn_dsl IR file: {loc or '(top)'}: {e.get('msg', '')}",
                                    hint="write IR JSON with `tnnc compile FILE.thn --emit ir-json -o OUT.ir.json`"))
        raise TnnError(diags) from None


# ---------------------------------------------------------------------------------------------
# DOT
# ---------------------------------------------------------------------------------------------

LEARNED_COLOR = "#d62728"
_STYLE = {
    "node": 'shape=ellipse, style=filled, fillcolor="#dbe9f6", color="#1f4e79"',
    "boundary": 'shape=box, style="filled,rounded", fillcolor="#e6e6e6", color="#555555"',
    "fluid_inlet": 'shape=cds, style=filled, fillcolor="#d9f2e6", color="#2e7d4f"',
    "source": 'shape=plaintext, fontcolor="#8c4a00"',
    "sensor": 'shape=note, style=filled, fillcolor="#fff7d6", color="#9a7b00"',
}


def _q(text: str) -> str:
    """A DOT double-quoted string."""
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'


def _value_text(pr: _Printer, name: str) -> str:
    """``R_hp1 = 0.2 K/W`` for constants, ``name = expr`` for derived, ``name ~ kind(args)`` for learned."""
    p = pr.params.get(name)
    if name in pr.targets:
        fn, _ = pr.targets[name]
        nominal = f" (nominal {pr.expr(p.expr)})" if p is not None else ""
        return f"{name} ~ {pr.kind_call(fn)}{nominal}"
    if p is None:
        return name
    if isinstance(p.expr, Num):
        text = f"{name} = {format_quantity(p.expr.value, p.expr.dim or p.dim, ascii_only=pr.ascii)}"
    else:
        text = f"{name} = {pr.expr(p.expr)}"
    return text + (" (free, per experiment)" if p.free and p.per_experiment else " (free)" if p.free else "")


def dot(net: Network) -> str:
    """Graphviz DOT text of the network (ends with a newline).

    Vertices: thermal nodes (ellipses, labelled with name, label and capacitance), boundaries (grey
    boxes with their temperature), fluid inlets, heat sources (plain text, arrow into the node), sensors
    (notes, dotted edge from the node they read). Edges: R/G links (labelled with the value and its SI
    unit), radiation (orange, dashed), Peltier elements (blue, bold, arrow to the hot side), fluids
    (green). Everything a learned function touches is red; learned heat loads are red arrows."""
    pr = _Printer(net)
    learned_flows = {t for t in pr.targets if "." in t}
    out = [f"digraph {_q(net.name)} {{"]
    title = net.name + (f"\n{net.label}" if net.label else "")
    out.append(f"  graph [label={_q(title)}, labelloc=t, fontsize=16, "
               "rankdir=LR, overlap=false, splines=true];")
    out.append('  node [fontname="Helvetica", fontsize=11];')
    out.append('  edge [fontname="Helvetica", fontsize=9, dir=none];')

    for n in net.nodes:
        cap = _value_text(pr, n.capacitance)
        label = n.name + (f"\n{n.label}" if n.label else "") + f"\n{cap}"
        extra = f', color="{LEARNED_COLOR}", penwidth=2' if n.capacitance in pr.targets else ""
        out.append(f"  {_q(n.name)} [label={_q(label)}, {_STYLE['node']}{extra}];")
    for b in net.boundaries:
        label = f"{b.name}\n{_value_text(pr, b.temperature)}"
        out.append(f"  {_q(b.name)} [label={_q(label)}, {_STYLE['boundary']}];")
    for f in net.fluids:
        vid = f"{f.name}.inlet"
        label = f"{f.name} inlet\n{pr.param(f.inlet)}"
        out.append(f"  {_q(vid)} [label={_q(label)}, {_STYLE['fluid_inlet']}];")

    for link in net.links:
        lab = _value_text(pr, link.value)
        if link.label:
            lab = f"{link.label}\n{lab}"
        learned = link.value in pr.targets
        style = f'color="{LEARNED_COLOR}", fontcolor="{LEARNED_COLOR}", penwidth=2.5' if learned else 'color="#333333"'
        out.append(f"  {_q(link.a)} -> {_q(link.b)} [label={_q(lab)}, {style}];")
    for r in net.radiations:
        lab = "\n".join([f"radiation {r.name}", *(_value_text(pr, x) for x in (r.area, r.emissivity, r.view_factor))])
        learned = any(x in pr.targets for x in (r.area, r.emissivity, r.view_factor))
        color = LEARNED_COLOR if learned else "#e07b00"
        out.append(f'  {_q(r.a)} -> {_q(r.b)} [label={_q(lab)}, color="{color}", fontcolor="{color}", style=dashed];')
    for pe in net.peltiers:
        parts = [f"Peltier {pe.name}"]
        for flow in ("Q_hot", "Q_cold"):
            key = f"{pe.name}.{flow}"
            if key in pr.targets:
                fn, _ = pr.targets[key]
                parts.append(f"{key} ~ {pr.kind_call(fn)}" + (" replaces physics" if fn.replace else ""))
        parts += [_value_text(pr, x) for x in (pe.current, pe.seebeck, pe.resistance) if x]
        if pe.r_internal:
            parts.append(_value_text(pr, pe.r_internal))
        learned = any(k in pr.targets for k in (f"{pe.name}.Q_hot", f"{pe.name}.Q_cold", pe.seebeck,
                                                 pe.resistance, pe.r_internal or ""))
        color = LEARNED_COLOR if learned else "#1f77b4"
        out.append(f"  {_q(pe.cold)} -> {_q(pe.hot)} [label={_q(chr(10).join(parts))}, color=\"{color}\", "
                   f"fontcolor=\"{color}\", penwidth=3, dir=forward, arrowhead=normal];")
    for f in net.fluids:
        parts = [f"fluid {f.name}"] + [_value_text(pr, x) for x in (f.mdot, f.cp, f.ua)]
        learned = f"{f.name}.Q" in learned_flows or any(x in pr.targets for x in (f.mdot, f.cp, f.ua))
        if f"{f.name}.Q" in pr.targets:
            fn, _ = pr.targets[f"{f.name}.Q"]
            parts.insert(1, f"{f.name}.Q ~ {pr.kind_call(fn)}")
        color = LEARNED_COLOR if learned else "#2e7d4f"
        out.append(f"  {_q(f.name + '.inlet')} -> {_q(f.node)} [label={_q(chr(10).join(parts))}, color=\"{color}\", "
                   f"fontcolor=\"{color}\", style=bold, dir=forward];")

    for src in net.sources:
        vid = f"source:{src.name}"
        learned = src.value in pr.targets
        color = LEARNED_COLOR if learned else "#8c4a00"
        out.append(f"  {_q(vid)} [label={_q(_value_text(pr, src.value))}, {_STYLE['source']}];")
        out.append(f'  {_q(vid)} -> {_q(src.node)} [color="{color}", dir=forward];')
    for fn in net.learned:
        for t in fn.targets:
            if t.kind == "heat_load":
                vid = f"heat_load:{t.name}"
                lab = f"Q[{t.name}] ~ {pr.kind_call(fn)}"
                out.append(f'  {_q(vid)} [label={_q(lab)}, shape=plaintext, fontcolor="{LEARNED_COLOR}"];')
                out.append(f'  {_q(vid)} -> {_q(t.name)} [color="{LEARNED_COLOR}", penwidth=2, dir=forward];')
    for s in net.sensors:
        vid = f"sensor:{s.name}"
        parts = [f"sensor {s.name}", f'column "{s.column}"']
        if s.lag:
            parts.append(_value_text(pr, s.lag))
        if s.offset:
            parts.append(_value_text(pr, s.offset))
        out.append(f"  {_q(vid)} [label={_q(chr(10).join(parts))}, {_STYLE['sensor']}];")
        out.append(f'  {_q(s.node)} -> {_q(vid)} [style=dotted, color="#9a7b00", dir=forward];')
    out.append("}")
    return "\n".join(out) + "\n"


def element_label(net: Network, name: str) -> tuple[str, bool]:
    """``(text, learned)``: a parameter's value as the DOT picture labels it (``"0.2 K/W"``, ``"learned"``...)
    and whether a learned function targets it (for other drawings of the network)."""
    pr = _Printer(net)
    return _value_text(pr, name), name in pr.targets
