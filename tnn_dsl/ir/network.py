"""The intermediate representation (IR): the single truth between parser, compiler, trainer,
sensitivity and diagnosis.

Everything here is plain data (pydantic models, JSON round-trippable). Nothing here knows about
syntax (that is :mod:`tnn_dsl.lang`) or tensors (that is :mod:`tnn_dsl.compiler`).

Conventions
-----------
* All numbers are SI: kelvin for temperatures (absolute), K/W, W/K, J/K, W, s, A, V/K, ohm, kg/s ...
* Every numeric slot of every element (a capacitance, a link's resistance, a Peltier's Seebeck
  coefficient, a heat source, a sensor lag ...) is a **parameter** in the one flat table
  ``Network.params``; the element stores the parameter's *name*. Parameters the user did not name get
  an automatic name (see ``auto_names`` in docs/architecture.md), so a learn clause, the trainer, the
  sensitivity pass and the diagnosis all address any slot the same way: by parameter name.
* A parameter's value is an :class:`Expr`. A literal (``Num``) is a constant and may be ``free``; any other
  expression is *derived* and may depend on other parameters, inputs and node temperatures (evaluated
  every step).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Callable, Iterator, Literal, Union

from pydantic import BaseModel, ConfigDict, Field

from ..core import Span

# ---------------------------------------------------------------------------------------------
# Source positions and dimensions
# ---------------------------------------------------------------------------------------------


Dim = dict[str, float]
"""A physical dimension as exponents over the SI base units ``kg m s K A mol cd``; ``{}`` is
dimensionless. Example: a resistance K/W is ``{"K": 1, "kg": -1, "m": -2, "s": 3}``."""


class _Node(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")
    span: Span | None = None


# ---------------------------------------------------------------------------------------------
# Expressions (no eval: a tree evaluated by ``_expr`` against an array namespace)
# ---------------------------------------------------------------------------------------------


class Num(_Node):
    """A literal quantity, already converted to SI. ``unit`` keeps the text the user wrote."""

    op: Literal["num"] = "num"
    value: float
    dim: Dim = Field(default_factory=dict)
    unit: str | None = None


class Ref(_Node):
    """A parameter or an input, by name (``kind`` is filled by the validation pass)."""

    op: Literal["ref"] = "ref"
    name: str
    kind: Literal["param", "input", "unresolved"] = "unresolved"


class Temp(_Node):
    """The temperature (K) of a node or a boundary: ``T(hx1)``, ``T3`` or a bare node name in a
    function argument list."""

    op: Literal["temp"] = "temp"
    node: str


class Unary(_Node):
    op: Literal["neg"] = "neg"
    arg: Expr


class Binary(_Node):
    op: Literal["+", "-", "*", "/", "^"]
    left: Expr
    right: Expr


CALL_FUNCTIONS = ("exp", "log", "sqrt", "min", "max", "abs", "series", "parallel", "mean")
"""Functions an expression may call. ``series(a, b) = a + b`` and ``parallel(a, b) = a·b/(a + b)`` for
resistances; ``mean`` is the arithmetic mean of its arguments (typically two temperatures)."""


class Call(_Node):
    op: Literal["call"] = "call"
    fn: Literal["exp", "log", "sqrt", "min", "max", "abs", "series", "parallel", "mean"]
    args: list[Expr]


class Table(_Node):
    """Piecewise-linear lookup ``table(x; x0: y0, x1: y1, ...)``; constant beyond the ends.
    ``xs`` strictly increasing, both lists in SI."""

    op: Literal["table"] = "table"
    x: Expr
    xs: list[float]
    ys: list[float]
    x_dim: Dim = Field(default_factory=dict)
    y_dim: Dim = Field(default_factory=dict)


Expr = Annotated[Union[Num, Ref, Temp, Unary, Binary, Call, Table], Field(discriminator="op")]

for _m in (Unary, Binary, Call, Table):
    _m.model_rebuild()


def walk(expr: Expr) -> Iterator[Expr]:
    """Every node of an expression tree, parents before children (iterative: deep trees are fine)."""
    stack = [expr]
    while stack:
        e = stack.pop()
        yield e
        if isinstance(e, Unary):
            stack.append(e.arg)
        elif isinstance(e, Binary):
            stack.extend([e.right, e.left])
        elif isinstance(e, Call):
            stack.extend(reversed(e.args))
        elif isinstance(e, Table):
            stack.append(e.x)


def map_children(expr: Expr, fn: Callable[[Expr], Expr]) -> Expr:
    """A copy of ``expr`` with ``fn`` applied to each direct child expression (the same node for a leaf):
    the one recursive step of every expression rewrite (``map_children(e, rewrite)`` inside ``rewrite``)."""
    if isinstance(expr, Unary):
        return expr.model_copy(update={"arg": fn(expr.arg)})
    if isinstance(expr, Binary):
        return expr.model_copy(update={"left": fn(expr.left), "right": fn(expr.right)})
    if isinstance(expr, Call):
        return expr.model_copy(update={"args": [fn(a) for a in expr.args]})
    if isinstance(expr, Table):
        return expr.model_copy(update={"x": fn(expr.x)})
    return expr


# ---------------------------------------------------------------------------------------------
# Declarations
# ---------------------------------------------------------------------------------------------

ParamRole = Literal[
    "resistance",  # K/W, positive
    "conductance",  # W/K, positive
    "capacitance",  # J/K, positive
    "temperature",  # K (boundary temperatures, fluid inlets, ambient params)
    "heat_flow",  # W (sources)
    "time_constant",  # s (sensor lag), positive
    "offset",  # K (sensor offset)
    "component",  # a component's coefficient: Seebeck, R_el, mdot, cp, UA, area, emissivity ...
    "generic",  # a user `param` not bound to a slot
]

POSITIVE_ROLES = ("resistance", "conductance", "capacitance", "time_constant")

SIGN_KEEPING_SLOTS = ("resistance", "seebeck", "mdot", "cp", "UA", "area", "emissivity", "view_factor")
"""A device's coefficients (role ``component``) that cannot change sign: an electrical resistance, a mass flow, a
heat capacity per kg, a conductance, an area, an emissivity, and a Peltier module's Seebeck coefficient (its sign
is fixed by which side the file calls hot). The current is not one of them."""


class Param(_Node):
    """One entry of the flat parameter table.

    ``expr`` is a ``Num`` for a constant (then ``free`` may be true and ``lower``/``upper`` bound it, SI)
    or any expression for a derived value. ``unit`` is the unit the user wrote (for display);
    ``dim`` its dimension. ``owner`` names the element whose slot this is (``"link R_hp1"``,
    ``"node hx1"``, ``"peltier pe"``) or ``None`` for a free-standing ``param``. ``per_experiment``
    (``free ... per experiment``, a free constant only): one value per data file.
    """

    name: str
    expr: Expr
    dim: Dim = Field(default_factory=dict)
    unit: str | None = None
    role: ParamRole = "generic"
    free: bool = False
    lower: float | None = None
    upper: float | None = None
    per_experiment: bool = False
    """The value differs per data file: fitted per training file, estimated from the burn-in of a held-out
    file; the written value is the starting value."""
    owner: str | None = None
    label: str | None = None

    @property
    def is_constant(self) -> bool:
        return isinstance(self.expr, Num)

    @property
    def value(self) -> float | None:
        """The SI value of a constant parameter, else ``None``."""
        return self.expr.value if isinstance(self.expr, Num) else None

    @property
    def keeps_sign(self) -> bool:
        """A value that cannot cross zero: a positive role (R, G, C, τ) or a device coefficient of
        :data:`SIGN_KEEPING_SLOTS` written in the device's line (``pe.resistance``, ``f2.UA``). A fit moves such a
        parameter as ``written·exp(θ)`` (a Peltier resistance fitted to −70.8 Ω absorbed a 0.3 K sensor offset)."""
        if self.role in POSITIVE_ROLES:
            return True
        return (self.role == "component" and self.owner is not None
                and self.name.rsplit(".", 1)[-1] in SIGN_KEEPING_SLOTS)


class Input(_Node):
    """A time series read from the data file. ``is_temperature`` inputs are converted to kelvin
    (from the file's temperature unit); others are scaled to SI by ``unit``."""

    name: str
    dim: Dim = Field(default_factory=dict)
    unit: str | None = None
    is_temperature: bool = False
    column: str
    label: str | None = None


class ThermalNode(_Node):
    """A node with a heat capacity: ``capacitance`` is a parameter name (J/K)."""

    name: str
    capacitance: str
    label: str | None = None


class Boundary(_Node):
    """A node of imposed temperature: ``temperature`` is a parameter name (K)."""

    name: str
    temperature: str
    label: str | None = None


class Link(_Node):
    """A linear conduction/convection path ``a -- b``. ``form`` says how the user gave it: ``value`` is a
    resistance parameter (K/W) for ``R``, a conductance parameter (W/K) for ``G``.
    Heat flow into ``a``: ``(T_b − T_a)/R`` or ``G·(T_b − T_a)``."""

    name: str
    a: str
    b: str
    form: Literal["R", "G"]
    value: str
    label: str | None = None


class Radiation(_Node):
    """Grey-body radiation ``Q_{b→a} = σ·ε·A·F·(T_b⁴ − T_a⁴)`` in absolute temperature."""

    name: str
    a: str
    b: str
    area: str
    emissivity: str
    view_factor: str


class Peltier(_Node):
    """Thermoelectric element (thesis eq. 2.12–2.13), absolute temperatures:
    ``Q_cold = −S·T_cold·I + ½·R_el·I²`` into ``cold``, ``Q_hot = S·T_hot·I + ½·R_el·I²`` into ``hot``,
    plus conduction through ``r_internal`` (K/W) between the two sides.
    Flows addressable by learn clauses: ``<name>.Q_hot``, ``<name>.Q_cold``."""

    name: str
    hot: str
    cold: str
    current: str
    seebeck: str
    resistance: str
    r_internal: str | None = None


class Fluid(_Node):
    """A fluid stream through ``node`` (thesis eq. 2.14): heat into the node
    ``Q = ṁ·cp·(1 − a)·(T_in − T_node)``, ``a = exp(−UA/(ṁ·cp))``. Flow name: ``<name>.Q``."""

    name: str
    node: str
    inlet: str
    mdot: str
    cp: str
    ua: str


class Source(_Node):
    """A heat load (W) into a node; ``value`` is a parameter name (often a derived expression)."""

    name: str
    node: str
    value: str


class Sensor(_Node):
    """What the data measures. Reads node ``node``; with ``lag`` (a time-constant parameter, s) the
    sensor has its own first-order state ``τ·dT_s/dt = T_node − T_s``; ``offset`` (K) is added to the
    reading. ``column`` is the data column."""

    name: str
    node: str
    column: str
    lag: str | None = None
    offset: str | None = None
    label: str | None = None


# ---------------------------------------------------------------------------------------------
# Learned functions
# ---------------------------------------------------------------------------------------------


class LearnTarget(_Node):
    """What a learned function produces.

    * ``param``: replaces a parameter (a resistance, conductance, capacitance, component coefficient);
      positive roles stay positive by construction; the untrained function returns the nominal value.
    * ``heat_load``: an extra heat flow (W) into node ``name`` (``Q[hx2]``); nominal 0.
    * ``flow``: replaces a component heat flow (``pe.Q_hot``, ``f1.Q``).
    """

    kind: Literal["param", "heat_load", "flow"]
    name: str


class LearnInput(_Node):
    """An argument of a learned function: a node's temperature (K), an input, or a parameter."""

    kind: Literal["node", "input", "param", "unresolved"] = "unresolved"
    name: str


LearnKind = Literal["const", "linear", "poly", "mlp", "table"]


class LearnFunction(_Node):
    """``learn T1, T2 as KIND(inputs; options)``. One function, several outputs (one per target).

    ``hidden`` and ``activation`` for ``mlp``; ``degree`` for ``poly``; ``knots`` (SI values of the
    single input) for ``table``. ``frozen`` keeps the function's weights fixed during training
    (loaded with ``init_from``, a model directory)."""

    name: str
    kind: LearnKind
    targets: list[LearnTarget]
    inputs: list[LearnInput] = Field(default_factory=list)
    hidden: list[int] = Field(default_factory=list)
    activation: Literal["sigmoid", "tanh", "relu", "softplus", "silu"] = "tanh"
    degree: int | None = None
    knots: list[float] = Field(default_factory=list)
    frozen: bool = False
    init_from: str | None = None
    replace: bool = False
    """For ``flow`` targets: the function replaces the physics flow instead of correcting it."""

    def weight_count(self) -> int:
        """How many trained numbers the function has, counted without building anything (``tnnc check``'s
        summary, the size cap): const ``n_out``; linear ``(n_in + 1)·n_out``; poly ``(n_monomials + 1)·n_out``
        with the monomials of degree 1..d; mlp ``Σ (fan_in + 1)·fan_out`` over its layers; table
        ``n_knots·n_out`` (``n_in = len(inputs)``, ``n_out = len(targets)``). The compiler's ``array_shapes``
        gives the same total (a test checks)."""
        n_in, n_out = len(self.inputs), len(self.targets)
        if self.kind == "const":
            return n_out
        if self.kind == "linear":
            return (n_in + 1) * n_out
        if self.kind == "poly":
            d = max(int(self.degree or 2), 1)
            return (math.comb(n_in + d, d) - 1 + 1) * n_out  # monomials of degree 1..d, and the bias
        if self.kind == "mlp":
            sizes = [n_in, *[int(h) for h in self.hidden], n_out]
            return sum((a + 1) * b for a, b in zip(sizes, sizes[1:]))
        return len(self.knots) * n_out  # table


# ---------------------------------------------------------------------------------------------
# The network
# ---------------------------------------------------------------------------------------------


class Network(BaseModel):
    """A validated network. Built only by ``tnn_dsl.load``/``loads`` (parser + validation pass) or
    ``Network.from_json``; use :meth:`graph` for the networkx view."""

    model_config = ConfigDict(extra="forbid")

    name: str
    label: str | None = None
    temperature_unit: Literal["degC", "K", "degF"] = "degC"
    source_files: list[str] = Field(default_factory=list)
    params: list[Param] = Field(default_factory=list)
    inputs: list[Input] = Field(default_factory=list)
    nodes: list[ThermalNode] = Field(default_factory=list)
    boundaries: list[Boundary] = Field(default_factory=list)
    links: list[Link] = Field(default_factory=list)
    radiations: list[Radiation] = Field(default_factory=list)
    peltiers: list[Peltier] = Field(default_factory=list)
    fluids: list[Fluid] = Field(default_factory=list)
    sources: list[Source] = Field(default_factory=list)
    sensors: list[Sensor] = Field(default_factory=list)
    learned: list[LearnFunction] = Field(default_factory=list)

    # -- lookups ---------------------------------------------------------------------------

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise KeyError(f"no parameter {name!r}; parameters are: {', '.join(p.name for p in self.params)}")

    @property
    def param_names(self) -> list[str]:
        return [p.name for p in self.params]

    @property
    def node_names(self) -> list[str]:
        return [n.name for n in self.nodes]

    @property
    def boundary_names(self) -> list[str]:
        return [b.name for b in self.boundaries]

    @property
    def input_names(self) -> list[str]:
        return [i.name for i in self.inputs]

    @property
    def free_params(self) -> list[Param]:
        return [p for p in self.params if p.free]

    def learned_targets(self) -> dict[str, tuple[LearnFunction, int]]:
        """``{target name: (function, output index)}``; heat loads are keyed ``Q[node]``."""
        out: dict[str, tuple[LearnFunction, int]] = {}
        for fn in self.learned:
            for i, t in enumerate(fn.targets):
                out[f"Q[{t.name}]" if t.kind == "heat_load" else t.name] = (fn, i)
        return out

    # -- views -----------------------------------------------------------------------------

    def graph(self) -> Any:
        """A ``networkx.MultiGraph``: vertices are nodes (``kind="node"``) and boundaries
        (``kind="boundary"``); edges are links, radiation, Peltier elements and fluids (a fluid is an
        edge from its node to a vertex ``"<fluid>.inlet"`` of kind ``"fluid_inlet"``). Edge data:
        ``kind``, ``name`` and the element itself under ``element``."""
        import networkx as nx

        g = nx.MultiGraph(name=self.name)
        for n in self.nodes:
            g.add_node(n.name, kind="node", element=n)
        for b in self.boundaries:
            g.add_node(b.name, kind="boundary", element=b)
        for link in self.links:
            g.add_edge(link.a, link.b, key=link.name, kind="link", name=link.name, element=link)
        for r in self.radiations:
            g.add_edge(r.a, r.b, key=r.name, kind="radiation", name=r.name, element=r)
        for pe in self.peltiers:
            g.add_edge(pe.hot, pe.cold, key=pe.name, kind="peltier", name=pe.name, element=pe)
        for f in self.fluids:
            g.add_node(f"{f.name}.inlet", kind="fluid_inlet", element=f)
            g.add_edge(f.node, f"{f.name}.inlet", key=f.name, kind="fluid", name=f.name, element=f)
        return g

    # -- serialisation ---------------------------------------------------------------------

    def to_json(self, indent: int | None = 2) -> str:
        return self.model_dump_json(indent=indent, exclude_defaults=False)

    @classmethod
    def from_json(cls, text: str) -> "Network":
        return cls.model_validate_json(text)


__all__ = [
    "Span", "Dim", "Num", "Ref", "Temp", "Unary", "Binary", "Call", "Table", "Expr", "CALL_FUNCTIONS", "walk",
    "map_children", "ParamRole", "POSITIVE_ROLES", "SIGN_KEEPING_SLOTS", "Param", "Input", "ThermalNode", "Boundary",
    "Link", "Radiation",
    "Peltier", "Fluid", "Source", "Sensor", "LearnTarget", "LearnInput", "LearnKind", "LearnFunction",
    "Network",
]
