"""The ``.thn`` printer: a validated :class:`~tnn_dsl.ir.Network` written back as a flat ``.thn`` file.

:func:`print_thn` is the inverse of :func:`tnn_dsl.lang.loads` on the IR: for every network the parser builds,
``loads(print_thn(net))`` gives the same IR (spans and ``source_files`` aside), and printing that again gives
the same text. The doctor builds its extended networks as IR edits and writes them through this printer.

What the file looks like
------------------------
* ``network``/``units`` header, the inputs, then the statements in the order of the parameter table (which is
  the order the parser met them, so a printed file keeps the user's order), the sensors that own no parameter,
  the ``learn`` clauses. A blank line separates runs of statements of different kinds. No comments (the IR has
  none); includes and subnets are already expanded, so the file is flat.
* Every numeric slot is printed inline in its element's line (``node h1 "heater 1"  C = 4 J/K  free``), with
  ``as NAME`` only where the statement allows it and the name is not the automatic one
  (docs/architecture.md, "auto_names"); other parameters are ``param`` lines.
* Quantities are printed in the unit the user wrote (``Num.unit``), bounds of ``free`` in the value's unit,
  with the shortest decimal that converts back to the same double (``4 J/K``, ``23 degC``, ``2.9 kWh/K``).
  Table points and learned-table knots, which the IR keeps in SI without a unit, are printed in SI units
  (temperatures in the file's temperature unit where that is exact).

What the language cannot say (these IR fields do not survive a print → parse round trip)
---------------------------------------------------------------------------------------
* **Learned-function names**: a ``learn`` clause's function is always named ``fn_<first target>`` by the
  parser, so other names (a ``learn`` inside a subnet: ``fn_R_wall``; the doctor's ``dx_params``) come back
  as the automatic name.
* **One-sided bounds**, and bounds on a parameter that is not ``free``: ``free in [LO, HI]`` has both or
  neither, so such a parameter is printed ``free`` without bounds (or without ``free``).
* **A free boundary temperature**: ``boundary`` has no ``free`` clause; it is printed fixed (and not
  ``per experiment``).
* **``per experiment`` on a parameter that is not free** (the validation pass refuses it): it is printed
  without it.
* **A slot whose parameter is not its automatic name** where the statement has no ``as`` (a node capacity
  not called ``C_<node>``, a sensor lag not called ``<sensor>.lag``, ...): the parameter is printed as a
  ``param`` line and the slot refers to it, so the re-read IR has one more parameter (the slot's automatic
  one, a reference). The parser never builds such a network.
* **Roles, owners and labels of parameters that belong to no element** (a ``param`` line is ``generic``);
  a derived parameter's ``unit``; labels of peltier, fluid and radiation statements (the IR keeps none).
* Node names that are not names (``r1.3``, a numbered node inside a subnet instance) cannot be printed at all:
  :func:`print_thn` raises ``ValueError``.
"""

from __future__ import annotations

import math
import re

from ..ir import (
    Binary,
    Call,
    LearnFunction,
    Network,
    Num,
    Param,
    Ref,
    Sensor,
    Table,
    Temp,
    Unary,
)
from .units import format_dim, unit_scale

__all__ = ["print_thn", "format_number"]

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_DEFAULT_HIDDEN = [8, 8]
_DEFAULT_DEGREE = 2

# precedence levels of the grammar: sum < product < unary (and a negative literal) < power < atom
_SUM, _PRODUCT, _UNARY, _POWER, _ATOM = 1, 2, 3, 4, 5
_OP_PREC = {"+": _SUM, "-": _SUM, "*": _PRODUCT, "/": _PRODUCT, "^": _POWER}


def print_thn(net: Network) -> str:
    """``net`` as the text of a flat ``.thn`` file (see the module doc for the layout and for what the language
    cannot express). Raises ``ValueError`` for a name that cannot be written (see module doc)."""
    return _ThnPrinter(net).text()


# ---------------------------------------------------------------------------------------------
# Numbers and quantities
# ---------------------------------------------------------------------------------------------


def format_number(value: float, unit: str | None = None) -> str:
    """The shortest decimal text ``x`` (with its sign) such that ``x UNIT`` reads back as exactly ``value``
    (SI; kelvin for a lone temperature unit). ``unit=None`` is a plain number. Falls back to 17 significant
    digits when no decimal in that unit converts to ``value`` exactly (a value computed in SI, written in a
    unit whose factor is not exact: off by about one unit in the last place)."""
    if not math.isfinite(value):
        raise ValueError(f"cannot print the non-finite number {value!r}")
    scale, offset = (1.0, 0.0) if not unit else unit_scale(unit)

    def back(text: str, negative: bool) -> float:
        x = -float(text) if negative else float(text)
        return x if not unit else x * scale + offset

    x = (value - offset) / scale
    negative = math.copysign(1.0, x) < 0
    ax = abs(x)
    for digits in range(1, 18):
        text = _plain(float(f"{ax:.{digits}g}"))
        if back(text, negative) == value:
            return ("-" if negative else "") + text
    near = [ax]  # the decimal that was written is within a few units in the last place of ``ax``
    up = down = ax
    for _ in range(8):
        up, down = math.nextafter(up, math.inf), math.nextafter(down, 0.0)
        near += [up, down]
    for cand in near:
        text = _plain(cand)
        if back(text, negative) == value:
            return ("-" if negative else "") + text
    return ("-" if negative else "") + f"{ax:.17g}"


def _plain(x: float) -> str:
    """The shortest text of a non-negative double that reads back as it (``repr``), without a trailing ``.0``
    or an exponent's ``+``: ``40``, ``0.05``, ``1e-05``, ``1e16``."""
    text = repr(x).replace("e+", "e")
    return text[:-2] if text.endswith(".0") else text


def _quantity(value: float, unit: str | None) -> str:
    """``value`` (SI) as ``NUMBER UNIT`` in ``unit`` (a plain number for ``None``)."""
    num = format_number(value, unit)
    return f"{num} {unit}" if unit else num


def _si_unit(dim: dict) -> str | None:
    """An SI unit text the grammar reads for a dimension (``None``: dimensionless)."""
    if not dim or not any(dim.values()):
        return None
    return format_dim(dim)


def _string(text: str) -> str:
    """A quoted ``.thn`` string (backslash, quote, newline and tab escaped)."""
    esc = text.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n").replace("\t", "\\t")
    return f'"{esc}"'


def _name(name: str) -> str:
    if not _NAME.match(name):
        raise ValueError(f"`{name}` cannot be written as a name in a .thn file")
    return name


def _node_id(name: str) -> str:
    """A node in a statement: a name, or a numbered node's number."""
    return name if name.isdigit() else _name(name)


def _slot_name(prefix: str, element: str) -> str:
    """The automatic name of a node's capacity (``C``) or a boundary's temperature (``T``); see
    ``tnn_dsl.lang.builder._slot_name``."""
    head, dot, tail = element.rpartition(".")
    return f"{head}.{prefix}_{tail}" if dot else f"{prefix}_{element}"


# ---------------------------------------------------------------------------------------------
# Expressions
# ---------------------------------------------------------------------------------------------


def _expr(e, temp_unit: str) -> tuple[str, int]:
    """(text, precedence level) of an expression, with the parentheses the grammar needs and no more."""
    if isinstance(e, Num):
        text = _quantity(e.value, e.unit)
        return text, (_UNARY if text.startswith("-") else _ATOM)
    if isinstance(e, Ref):
        return _name(e.name), _ATOM
    if isinstance(e, Temp):
        return f"T({_node_id(e.node)})", _ATOM
    if isinstance(e, Unary):
        arg, prec = _expr(e.arg, temp_unit)
        # a literal is parenthesised: `-5 degC` is the literal minus five degrees, `-(5 degC)` its negation
        if prec < _UNARY or isinstance(e.arg, Num):
            arg = f"({arg})"
        return f"-{arg}", _UNARY
    if isinstance(e, Binary):
        return _binary(e, temp_unit)
    if isinstance(e, Call):
        return f"{e.fn}({', '.join(_expr(a, temp_unit)[0] for a in e.args)})", _ATOM
    if isinstance(e, Table):
        x_unit = _point_unit(e.xs, e.x_dim, temp_unit)
        y_unit = _point_unit(e.ys, e.y_dim, temp_unit)
        pts = ", ".join(f"{_quantity(x, x_unit)}: {_quantity(y, y_unit)}" for x, y in zip(e.xs, e.ys))
        return f"table({_expr(e.x, temp_unit)[0]}; {pts})", _ATOM
    raise ValueError(f"cannot print the expression {e!r}")


def _binary(e: Binary, temp_unit: str) -> tuple[str, int]:
    prec = _OP_PREC[e.op]
    left, lp = _expr(e.left, temp_unit)
    right, rp = _expr(e.right, temp_unit)
    if e.op == "^":
        # the base is an atom; a literal with a unit is bracketed (`(2 m)^2`: `2 m^2` is two square metres)
        if lp < _ATOM or (isinstance(e.left, Num) and e.left.unit):
            left = f"({left})"
        if rp < _UNARY:
            right = f"({right})"
        return f"{left}^{right}", prec
    if lp < prec:
        left = f"({left})"
    if rp < (_PRODUCT if prec == _SUM else _UNARY):  # `a - (b + c)`, `a / (b * c)`
        right = f"({right})"
    return f"{left} {e.op} {right}", prec


def _point_unit(values: list[float], dim: dict, temp_unit: str) -> str | None:
    """The unit of a table's x or y points: the file's temperature unit for plausible absolute temperatures
    (150–1000 K), else SI."""
    unit = _si_unit(dim)
    if unit == "K" and values and all(150.0 <= v <= 1000.0 for v in values):
        return temp_unit
    return unit


# ---------------------------------------------------------------------------------------------
# The file
# ---------------------------------------------------------------------------------------------


class _ThnPrinter:
    """One network being printed: which element owns which parameter, the automatic-name counters of the
    parser (to know where ``as NAME`` is needed), and the statements emitted so far."""

    def __init__(self, net: Network):
        self.net = net
        self.tu = net.temperature_unit
        self.params = {p.name: p for p in net.params}
        self.lines: list[str] = []
        self.last_kind: str | None = None
        self.auto_counts: dict[str, int] = {}
        self.kinds = {"node": net.nodes, "boundary": net.boundaries, "link": net.links, "radiation": net.radiations,
                      "peltier": net.peltiers, "fluid": net.fluids, "source": net.sources, "sensor": net.sensors}
        self.done: dict[str, int] = {k: 0 for k in self.kinds}  # elements of each kind printed (in list order)
        self.owner: dict[str, tuple[str, int]] = {}  # param name -> (kind, index) of the element printing it
        for kind, elements in self.kinds.items():
            for i, el in enumerate(elements):
                for pname, auto in self._slots(kind, el):
                    if pname is not None and pname == auto and pname in self.params and pname not in self.owner:
                        self.owner[pname] = (kind, i)

    @staticmethod
    def _slots(kind: str, el) -> list[tuple[str | None, str]]:
        """(parameter name, its automatic name) of each numeric slot of an element."""
        n = el.name
        if kind == "node":
            return [(el.capacitance, _slot_name("C", n))]
        if kind == "boundary":
            return [(el.temperature, _slot_name("T", n))]
        if kind in ("link", "source"):
            return [(el.value, n)]
        if kind == "sensor":
            return [(el.lag, f"{n}.lag"), (el.offset, f"{n}.offset")]
        if kind == "radiation":
            return [(el.area, f"{n}.area"), (el.emissivity, f"{n}.emissivity"),
                    (el.view_factor, f"{n}.view_factor")]
        if kind == "peltier":
            return [(el.current, f"{n}.current"), (el.seebeck, f"{n}.seebeck"), (el.resistance, f"{n}.resistance"),
                    (el.r_internal, f"{n}.R_internal")]
        return [(el.inlet, f"{n}.inlet"), (el.mdot, f"{n}.mdot"), (el.cp, f"{n}.cp"), (el.ua, f"{n}.UA")]

    # -- output ---------------------------------------------------------------------------------

    def emit(self, kind: str, line: str) -> None:
        if self.last_kind is not None and kind != self.last_kind:
            self.lines.append("")
        self.lines.append(line)
        self.last_kind = kind

    def text(self) -> str:
        net = self.net
        self.emit("network", f"network {_name(net.name)}" + (f" {_string(net.label)}" if net.label else ""))
        self.emit("network", f"units temperature = {net.temperature_unit}")
        for inp in net.inputs:
            self.emit("input", self.input_line(inp))
        for p in net.params:
            if p.name in self.owner:
                kind, i = self.owner[p.name]
                self.element_upto(kind, i + 1)
            else:
                self.emit("param", self.param_line(p))
        for kind, elements in self.kinds.items():  # elements that own no parameter printed so far
            self.element_upto(kind, len(elements))
        for fn in net.learned:
            self.emit("learn", self.learn_line(fn))
        return "\n".join(self.lines) + "\n"

    def element_upto(self, kind: str, stop: int) -> None:
        """Print the elements of ``kind`` not yet printed, up to index ``stop`` (exclusive), in list order."""
        elements = self.kinds[kind]
        while self.done[kind] < stop:
            el = elements[self.done[kind]]
            self.done[kind] += 1
            self.emit(kind, getattr(self, f"{kind}_line")(el))

    # -- pieces ---------------------------------------------------------------------------------

    def auto_as(self, base: str, name: str) -> str:
        """``""`` where the parser's automatic name (``base``, ``base_2`` ... on repeats) is ``name`` (and count
        it, as the parser does), else ``"  as NAME"``."""
        n = self.auto_counts.get(base, 0) + 1
        if name == (base if n == 1 else f"{base}_{n}"):
            self.auto_counts[base] = n
            return ""
        return f"  as {_name(name)}"

    def value(self, pname: str | None, auto: str, *, free_ok: bool = True) -> str:
        """The text of a slot: its expression with ``free [in [LO, HI]] [per experiment]`` where the slot owns the
        parameter, else a reference to the parameter (printed as a ``param`` line, see module doc)."""
        if pname is None:
            return ""
        if pname != auto or pname not in self.params:
            return _name(pname)
        return self.expr_free(self.params[pname], free_ok=free_ok)

    def expr_free(self, p: Param, *, free_ok: bool = True) -> str:
        """A constant's value with ``free [in [LO, HI]] [per experiment]``; any other expression as it is."""
        text = _expr(p.expr, self.tu)[0]
        if not (free_ok and p.free and isinstance(p.expr, Num)):
            return text
        text += "  free"
        if p.lower is not None and p.upper is not None:
            text += f" in [{_quantity(p.lower, p.expr.unit)}, {_quantity(p.upper, p.expr.unit)}]"
        return text + (" per experiment" if p.per_experiment else "")

    def input_line(self, inp) -> str:
        if inp.is_temperature and inp.unit == self.tu:
            kind = "temperature"
        else:
            kind = f"[{inp.unit or '1'}]"
        line = f"input {_name(inp.name)} : {kind}"
        if inp.label:
            line += f"  {_string(inp.label)}"
        if inp.column != inp.name:
            line += f"  column {_string(inp.column)}"
        return line

    def param_line(self, p: Param) -> str:
        line = f"param {_name(p.name)} = {self.expr_free(p)}"
        return line + (f"  {_string(p.label)}" if p.label else "")

    @staticmethod
    def _label(el) -> str:
        return f" {_string(el.label)}" if getattr(el, "label", None) else ""

    def node_line(self, n) -> str:
        c = self.value(n.capacitance, _slot_name("C", n.name))
        return f"node {_node_id(n.name)}{self._label(n)}  C = {c}"

    def boundary_line(self, b) -> str:
        t = self.value(b.temperature, _slot_name("T", b.name), free_ok=False)
        return f"boundary {_node_id(b.name)}{self._label(b)} = {t}"

    def link_line(self, lk) -> str:
        a, b = _node_id(lk.a), _node_id(lk.b)
        as_ = self.auto_as(f"{lk.form}_{lk.a}_{lk.b}", lk.name)
        return f"{lk.form} {a} -- {b}{self._label(lk)} = {self.value(lk.value, lk.name)}{as_}"

    def source_line(self, s) -> str:
        as_ = self.auto_as(f"Q_src_{s.node}", s.name)
        p = self.params.get(s.value)
        label = f"  {_string(p.label)}" if p is not None and p.label and s.value == s.name else ""
        return f"source {_node_id(s.node)} = {self.value(s.value, s.name)}{as_}{label}"

    def sensor_line(self, s: Sensor) -> str:
        line = f"sensor {_name(s.name)}{self._label(s)} = {_node_id(s.node)}"
        if s.lag is not None:
            line += f"  lag {self.value(s.lag, f'{s.name}.lag')}"
        if s.offset is not None:
            line += f"  offset {self.value(s.offset, f'{s.name}.offset')}"
        if s.column != s.name:
            line += f"  column {_string(s.column)}"
        return line

    def radiation_line(self, r) -> str:
        as_ = self.auto_as(f"rad_{r.a}_{r.b}", r.name)
        line = f"radiation {_node_id(r.a)} -- {_node_id(r.b)}"
        line += f"  area = {self.value(r.area, f'{r.name}.area')}"
        line += f"  emissivity = {self.value(r.emissivity, f'{r.name}.emissivity')}"
        vf = self.params.get(r.view_factor)
        default_vf = (vf is not None and r.view_factor == f"{r.name}.view_factor" and isinstance(vf.expr, Num)
                      and vf.expr.value == 1.0 and vf.expr.unit is None and not vf.free)
        if not default_vf:
            line += f"  view_factor = {self.value(r.view_factor, f'{r.name}.view_factor')}"
        return line + as_

    def peltier_line(self, pe) -> str:
        n = pe.name
        line = f"peltier {_name(n)}  hot = {_node_id(pe.hot)}  cold = {_node_id(pe.cold)}"
        line += f"  current = {self.value(pe.current, f'{n}.current')}"
        line += f"  seebeck = {self.value(pe.seebeck, f'{n}.seebeck')}"
        line += f"  resistance = {self.value(pe.resistance, f'{n}.resistance')}"
        if pe.r_internal is not None:
            line += f"  R_internal = {self.value(pe.r_internal, f'{n}.R_internal')}"
        return line

    def fluid_line(self, f) -> str:
        n = f.name
        return (f"fluid {_name(n)}  through {_node_id(f.node)}  inlet = {self.value(f.inlet, f'{n}.inlet')}"
                f"  mdot = {self.value(f.mdot, f'{n}.mdot')}  cp = {self.value(f.cp, f'{n}.cp')}"
                f"  UA = {self.value(f.ua, f'{n}.UA')}")

    # -- learn ----------------------------------------------------------------------------------

    def learn_input(self, kind: str, name: str) -> str:
        """A learned function's argument: a node by its bare name (``T3`` for numbered node 3) where that
        cannot be read as an input or a parameter, else ``T(node)``."""
        if kind != "node":
            return _name(name)
        net = self.net
        values = set(net.input_names) | set(self.params)
        if name.isdigit():
            bare = f"T{name}"
            clash = bare in values or bare in net.node_names or bare in net.boundary_names
            return f"T({name})" if clash else bare
        return f"T({_name(name)})" if name in values else _name(name)

    def knot_unit(self, fn: LearnFunction) -> str | None:
        """The unit of a learned table's knots: that of its single argument."""
        if not fn.inputs:
            return None
        li = fn.inputs[0]
        if li.kind == "node":
            return self.tu
        for inp in self.net.inputs:
            if inp.name == li.name:
                return inp.unit if inp.unit not in (None, "", "1") else None
        p = self.params.get(li.name)
        if p is not None:
            return p.expr.unit if isinstance(p.expr, Num) and p.expr.unit else _si_unit(p.dim)
        return None

    def learn_line(self, fn: LearnFunction) -> str:
        targets = ", ".join(f"Q[{_node_id(t.name)}]" if t.kind == "heat_load" else _name(t.name)
                            for t in fn.targets)
        args = [self.learn_input(li.kind, li.name) for li in fn.inputs]
        opts: list[str] = []
        if fn.kind == "mlp":
            opts.append(f"hidden = [{', '.join(str(h) for h in (fn.hidden or _DEFAULT_HIDDEN))}]")
            if fn.activation != "tanh":
                opts.append(f"activation = {fn.activation}")
        elif fn.kind == "poly":
            opts.append(f"degree = {fn.degree if fn.degree is not None else _DEFAULT_DEGREE}")
        elif fn.kind == "table":
            unit = self.knot_unit(fn)
            opts.append(f"knots = [{', '.join(_quantity(k, unit) for k in fn.knots)}]")
        if fn.replace:
            opts.append("replace")
        if fn.frozen:
            opts.append("frozen")
        if fn.init_from is not None:
            opts.append(f"init_from = {_string(fn.init_from)}")
        line = f"learn {targets} as {fn.kind}"
        if args:
            return line + f"({', '.join(args)}" + (f"; {', '.join(opts)}" if opts else "") + ")"
        return line + "".join(f" {o}" for o in opts)  # `as const replace`
