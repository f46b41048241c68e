"""The ``.thn`` printer (``tnn_dsl.lang.printer.print_thn``): parse → print → parse gives the same IR for every
network of networks/ and every example of the language spec, printing is a fixed point, and random edits of
parameter values and random expression trees round-trip exactly (to the bit)."""

from __future__ import annotations

import glob
import math
import os
import re

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from test_spec_examples import (
    DESIGN_CARD,
    DESIGN_CARD_CONTEXT,
    M2,
    M2_BODY,
    TCLAB,
    TCLAB_MISSES,
    VARIANTS,
)

import tnn_dsl
from tnn_dsl import TnnError
from tnn_dsl.ir import Binary, Call, Network, Num, Param, Ref, Table, Unary
from tnn_dsl.lang import parse_quantity, print_thn, validate
from tnn_dsl.lang.printer import format_number

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NETWORKS = sorted(glob.glob(os.path.join(ROOT, "networks", "**", "*.thn"), recursive=True))
SPEC = os.path.join(os.path.dirname(ROOT), "shared", "spec", "thn-by-example.md")

SECTION3 = M2_BODY + '''
param R_hp_true = 0.2 K/W * (1 + 1.5*(u1 - 0.5) - 0.02 1/K * (mean(T(hx1), T(hp)) - 25 degC))
node cu C = 10 J/K
G cu -- amb = table(mean(cu, amb); 0 degC: 2.0 W/K, 50 degC: 2.4 W/K)
R cu -- base = series(1 K/W, parallel(2 K/W, 2 K/W))
learn Q[hx2] as mlp(hx2, u1)
learn pe.seebeck as poly(ph, pc; degree = 2)
learn C_hp as table(hp; knots = [0 degC, 25 degC, 50 degC])
'''

# the spec's examples, as tests/test_spec_examples.py holds them (whole networks)
SPEC_EXAMPLES = {
    "tclab": TCLAB,
    "tclab_misses": TCLAB.replace('sensor T1 = h1  column "T1_degC"    # what the data measures, and where\n', "")
    + TCLAB_MISSES,
    "m2": M2,
    **{v.lower(): M2_BODY + clause + "\n" for v, clause in VARIANTS.items()},
    "m5": M2_BODY + 'learn pe.Q_hot, pe.Q_cold as mlp(ph, pc, I; hidden = [8, 8], frozen, init_from = "models/m4")\n'
    "learn R_hp1, R_hp2, R_hpa as mlp(hx1, hp, hx2, u1; hidden = [8, 8], activation = sigmoid)\n",
    "design_card": DESIGN_CARD_CONTEXT + DESIGN_CARD,
    "section3": SECTION3,
}

# every corner of the language the printer must get right, in one network
CORNERS = r'''
network corners "a \"quoted\" label\twith a tab"
units temperature = K
input u : [1]
input P : [kW]  "power"  column "P_kW"
input Tx : [degC]
input Tin : temperature
param k = 2 free
param e = 0.5 free in [0.1, 0.9]  "dimensionless, bounded"
param Tday = 20 degC free in [10 degC, 30 degC] per experiment  "ambient of each data file"
param Pday = 0 W free per experiment
param neg = -5 degC
param minus = -(5 degC)
param d = 2 - (3 - u) - -u / (4 * u) * 2^-1 + (-2)^2 - (2 m)^2 / 1 m^2 + exp(-u)^(1 + u)^2
param big = 1e22 J/K
param small = 1.5e-12 W/K
param third = 0.3333333333333333
node 3 C = 300 J/K
node T3 C = 1 J/K
node x "x node" C = 2.9 kWh/K  free in [0.1 kWh/K, 10 kWh/K]
boundary 9 = 300
boundary amb = Tin
R 3 -- amb = 1 K/W
R 3 -- amb = 2 K/W
R 3 -- amb = 3 K/W  as R_3_amb_3
G x -- amb "outer" = 0.5 W/K  as R_3_amb_2b
G T3 -- 9 = table(T(T3) - T(9); -5 K: 1 W/K, 5 K: 2 W/K)
R x -- 3 = series(1 K/W, parallel(2 K/W, 3 K/W), min(1 K/W, 2 K/W))
radiation x -- amb  area = 1e-3 m^2  emissivity = 0.9  view_factor = 0.5  as rad1
radiation 3 -- amb  area = 2 m^2 free in [1 m^2, 3 m^2]  emissivity = 1
radiation 3 -- amb  area = 2 m^2  emissivity = 1  view_factor = 1 free in [0.5, 1]
peltier pe  hot = x  cold = 3  current = 2 A  seebeck = 0.05 V/K  resistance = 2 ohm
fluid f1  through x  inlet = 20 degC  mdot = 2 g/s  cp = 4.186 kJ/(kg*K)  UA = 5 W/K free
source x = P  as Qp  "heater"
source 3 = 1 W
source 3 = 2 W
sensor s1 "first" = x  lag 20 s  offset 0.5 K free in [-1 K, 1 K]  column "S 1"
sensor s2 = 3  offset 0 K
sensor s3 = T3
sensor s4 = x  offset 0 K free per experiment  lag 5 s free in [1 s, 9 s] per experiment
G x -- 9 = 1 W/K  as Gday  per experiment free
learn R_3_amb as linear(T(3), T(T3), u, k)
learn Q[x] as table(Tx; knots = [0 degC, 50 degC])
learn Q[3] as table(T(3); knots = [280, 300])
learn Q[T3], R_3_amb_2 as poly(u; degree = 3)
learn f1.Q as const replace
learn pe.Q_hot as mlp(u; hidden = [4], activation = relu, replace)
'''


def ir(net: Network) -> dict:
    """The IR as a plain dict without source positions and file names (what a round trip must keep)."""
    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in ("span", "source_files")}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    return strip(net.model_dump())


def round_trip(net: Network, filename: str = "printed.thn") -> tuple[str, Network]:
    text = print_thn(net)
    back = tnn_dsl.loads(text, filename)
    assert ir(back) == ir(net), text
    assert print_thn(back) == text  # printing is a fixed point
    return text, back


def _spec_blocks() -> list[str]:
    """The code blocks of the spec file (when the checkout has it) that are whole networks."""
    if not os.path.isfile(SPEC):
        return []
    with open(SPEC, encoding="utf-8") as f:
        blocks = re.findall(r"```\n(.*?)```", f.read(), re.S)
    return [b for b in blocks if b.lstrip().startswith("network ")]


@pytest.mark.parametrize("path", NETWORKS, ids=[os.path.relpath(p, ROOT) for p in NETWORKS])
def test_every_network_round_trips(path):
    net = tnn_dsl.load(path)
    text, _ = round_trip(net, path)
    assert not re.search(r"^(include|subnet|use) ", text, re.M)  # the flat result


@pytest.mark.parametrize("name", sorted(SPEC_EXAMPLES))
def test_every_spec_example_round_trips(name, tmp_path):
    path = tmp_path / f"{name}.thn"
    path.write_text(SPEC_EXAMPLES[name])
    round_trip(tnn_dsl.load(path), str(path))


def test_the_spec_files_own_blocks_round_trip():
    blocks = _spec_blocks()
    if not os.path.isfile(SPEC):
        pytest.skip("../shared/spec/thn-by-example.md is not in this checkout")
    assert len(blocks) >= 2
    for text in blocks:
        round_trip(tnn_dsl.loads(text, "spec.thn"))


def test_corners_round_trip():
    text, back = round_trip(tnn_dsl.loads(CORNERS, "corners.thn"))
    assert back.param("big").value == 1e22 and back.param("third").value == 1 / 3
    assert back.param("neg").expr.value == pytest.approx(268.15)  # the literal `-5 degC`
    minus = back.param("minus").expr
    assert isinstance(minus, Unary) and minus.arg.value == pytest.approx(278.15)  # `-(5 degC)`, negated
    for line in ("param neg = -5 degC", "param minus = -(5 degC)", "node x \"x node\"  C = 2.9 kWh/K",
                 "R 3 -- amb = 2 K/W\n", "R 3 -- amb = 3 K/W\n", "as R_3_amb_2b", "boundary 9 = 300 K",
                 "learn Q[T3], R_3_amb_2 as poly(",
                 'param Tday = 20 degC  free in [10 degC, 30 degC] per experiment  "ambient of each data file"',
                 "param Pday = 0 W  free per experiment\n", "offset 0 K  free per experiment",
                 "lag 5 s  free in [1 s, 9 s] per experiment", "G x -- 9 = 1 W/K  free per experiment  as Gday"):
        assert line in text
    assert {p.name for p in back.params if p.per_experiment} == {"Tday", "Pday", "s4.lag", "s4.offset", "Gday"}
    # `T3` in a learn argument list is the node called T3 where there is one; node 3 is then `T(3)`
    assert "learn R_3_amb as linear(T(3), T3, u, k)" in text


def test_numbers_are_short_and_exact():
    assert format_number(40.0, "J/K") == "40"
    assert format_number(parse_quantity(23, "degC")[0], "degC") == "23"
    assert format_number(parse_quantity(-5, "degC")[0], "degC") == "-5"
    assert format_number(parse_quantity(2.9, "kWh/K")[0], "kWh/K") == "2.9"
    assert format_number(parse_quantity(0.01, "W/%")[0], "W/%") == "0.01"
    assert format_number(1e-5) == "1e-05" and format_number(1e16) == "1e16"
    for x in (1 / 3, math.pi * 1e-7, 123456.789123, 6.02214076e23):
        for unit in ("kJ/K", "degF", "K/kW", None):
            text = format_number(parse_quantity(x, unit)[0], unit)
            assert parse_quantity(float(text), unit)[0] == parse_quantity(x, unit)[0]


def test_every_element_kind_is_printed():
    """The corpus holds every kind of element, and the printer writes one line for each element."""
    nets = [tnn_dsl.load(p) for p in NETWORKS] + [tnn_dsl.loads(CORNERS, "corners.thn")]
    seen = set()
    for net in nets:
        text = print_thn(net)
        lines = text.splitlines()
        count = {k: sum(1 for ln in lines if ln.startswith(k + " "))
                 for k in ("input", "param", "node", "boundary", "radiation", "peltier", "fluid", "source",
                           "sensor", "learn")}
        links = sum(1 for ln in lines if re.match(r"^[RG] \S+ -- ", ln))
        assert count["node"] == len(net.nodes) and count["boundary"] == len(net.boundaries)
        assert links == len(net.links) and count["radiation"] == len(net.radiations)
        assert count["peltier"] == len(net.peltiers) and count["fluid"] == len(net.fluids)
        assert count["source"] == len(net.sources) and count["sensor"] == len(net.sensors)
        assert count["learn"] == len(net.learned) and count["input"] == len(net.inputs)
        owned = sum(1 for p in net.params if p.owner is None)
        assert count["param"] == owned
        seen |= {k for k, v in count.items() if v} | ({"link"} if links else set())
        seen |= {f"link {lk.form}" for lk in net.links} | {f"learn {fn.kind}" for fn in net.learned}
        seen |= {"free in"} if any(p.free and p.lower is not None for p in net.params) else set()
        seen |= {"lag"} if any(s.lag for s in net.sensors) else set()
        seen |= {"offset"} if any(s.offset for s in net.sensors) else set()
        seen |= {"frozen"} if any(fn.frozen for fn in net.learned) else set()
    kinds = {"input", "param", "node", "boundary", "link", "link R", "link G", "radiation", "peltier", "fluid",
             "source", "sensor", "learn", "free in", "lag", "offset", "frozen",
             *(f"learn {k}" for k in ("const", "linear", "poly", "mlp", "table"))}
    assert kinds <= seen, kinds - seen


# -- what the language cannot say (see the printer's module doc) ---------------------------------------------


def test_not_expressible_learned_function_names():
    net = tnn_dsl.load(os.path.join(ROOT, "networks", "peltier_heatpipe", "m2.thn"))
    renamed = net.model_copy(update={"learned": [net.learned[0].model_copy(update={"name": "dx_params"})]})
    back = tnn_dsl.loads(print_thn(renamed), "m2.thn")
    assert back.learned[0].name == "fn_R_hp1"  # always the automatic name


def test_not_expressible_one_sided_bounds_and_a_free_boundary():
    net = tnn_dsl.loads(TCLAB, "tclab.thn")
    one_sided = [p.model_copy(update={"upper": None}) if p.name == "Ta" else p for p in net.params]
    one_sided = [p.model_copy(update={"free": True}) if p.name == "T_amb" else p for p in one_sided]
    text = print_thn(net.model_copy(update={"params": one_sided}))
    assert "param Ta = 23 degC  free\n" in text and "boundary amb = Ta\n" in text
    back = tnn_dsl.loads(text, "tclab.thn")
    assert back.param("Ta").lower is None and not back.param("T_amb").free


def test_not_expressible_a_slot_with_another_name():
    net = tnn_dsl.loads(TCLAB, "tclab.thn")
    params = [p.model_copy(update={"name": "cap1"}) if p.name == "C_h1" else p for p in net.params]
    nodes = [n.model_copy(update={"capacitance": "cap1"}) if n.name == "h1" else n for n in net.nodes]
    text = print_thn(net.model_copy(update={"params": params, "nodes": nodes}))
    assert "param cap1 = 4 J/K  free" in text and 'node h1 "heater 1"  C = cap1' in text
    back = tnn_dsl.loads(text, "tclab.thn")
    c = back.param("C_h1").expr  # one more parameter: the automatic one, a reference
    assert isinstance(c, Ref) and (c.name, c.kind) == ("cap1", "param")


def test_a_name_that_is_not_a_name_is_refused():
    net = tnn_dsl.loads(TCLAB, "tclab.thn")
    with pytest.raises(ValueError, match="r1.3"):
        print_thn(net.model_copy(update={"nodes": [net.nodes[0].model_copy(update={"name": "r1.3"})]}))


# -- properties ----------------------------------------------------------------------------------------------

_BASES = {os.path.basename(p): tnn_dsl.load(p) for p in NETWORKS}


@st.composite
def edited_network(draw):
    """A network of networks/ with some constants changed: new values (as decimals in their unit), ``free``
    flipped, bounds set or removed, ``per experiment`` flipped on free constants that nothing learns."""
    net = _BASES[draw(st.sampled_from(sorted(_BASES)))]
    learned = net.learned_targets()
    params = []
    for p in net.params:
        if isinstance(p.expr, Num) and draw(st.booleans()):
            unit = p.expr.unit
            x = draw(st.floats(0.5, 2.0)) * (p.expr.value if unit is None else format_value(p.expr.value, unit))
            value = parse_quantity(x, unit)[0]
            free = draw(st.booleans())
            lower = upper = None
            if free and draw(st.booleans()):
                lo, hi = x - draw(st.floats(0.0, 0.99)) * abs(x), x + draw(st.floats(0.0, 10.0)) * abs(x) + 1e-3
                lower, upper = parse_quantity(lo, unit)[0], parse_quantity(hi, unit)[0]
            per = free and p.name not in learned and draw(st.booleans())
            p = p.model_copy(update={"expr": p.expr.model_copy(update={"value": value}), "free": free,
                                     "lower": lower, "upper": upper, "per_experiment": per})
        params.append(p)
    edited = net.model_copy(update={"params": params})
    try:
        return validate(edited)
    except TnnError:
        assume(False)


def format_value(value_si: float, unit: str) -> float:
    """A value in SI written as the number in ``unit``."""
    return float(format_number(value_si, unit))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(edited_network())
def test_random_parameter_edits_round_trip(net):
    round_trip(net)


_LEAF = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False).map(lambda v: Num(value=v)),
    st.sampled_from([Ref(name="u", kind="input"), Ref(name="k", kind="param")]),
)


def _tree(children):
    unary = children.map(lambda a: Unary(arg=a))
    binary = st.tuples(st.sampled_from("+-*/^"), children, children).map(
        lambda t: Binary(op=t[0], left=t[1], right=t[2]))
    one = st.tuples(st.sampled_from(["exp", "log", "sqrt", "abs", "min", "max", "mean"]), children).map(
        lambda t: Call(fn=t[0], args=[t[1]]))
    many = st.tuples(st.sampled_from(["min", "max", "mean", "series", "parallel"]),
                     st.lists(children, min_size=2, max_size=3)).map(lambda t: Call(fn=t[0], args=t[1]))
    table = st.tuples(children, st.lists(st.floats(-100, 100), min_size=2, max_size=4, unique=True)).map(
        lambda t: Table(x=t[0], xs=sorted(t[1]), ys=list(t[1])))
    return st.one_of(binary, binary, binary, binary, unary, one, many, table)  # mostly operators: precedence


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.recursive(_LEAF, _tree, max_leaves=16))
def test_random_expressions_round_trip(expr):
    net = _expr_net(expr)
    assume(net is not None)
    round_trip(net)


def _expr_net(expr) -> Network | None:
    """The test network with the parameter ``g = expr``; ``None`` where validation rejects the value of a constant
    part of ``expr`` (``u / 0``, ``log(-1)``: tests/test_values_checked.py)."""
    base = tnn_dsl.loads("network e\ninput u : [1]\nparam k = 2\nboundary b = 20 degC\nnode n C = 1 J/K\n"
                         "G n -- b = 1 W/K\n", "e.thn")
    try:
        return validate(base.model_copy(update={"params": list(base.params) + [Param(name="g", expr=expr)]}))
    except TnnError as err:
        if all(" in `g`" in d.message or d.message.startswith("`g` is not") for d in err.diagnostics):
            return None
        raise


_SMALL = [Ref(name="u", kind="input"), Num(value=2.0), Num(value=-3.0), Num(value=50.0, unit="%"),
          Unary(arg=Ref(name="k", kind="param")), Unary(arg=Num(value=4.0))]


@pytest.mark.parametrize("outer", list("+-*/^") + ["neg"])
def test_every_operator_pair_round_trips(outer):
    """Every operator (and negation) over every operator, a negative literal and a literal with a unit (`%`), on
    either side: the parentheses the printer writes are the ones the grammar needs (`(2 m)^2`: CORNERS)."""
    inner = [Binary(op=op, left=a, right=b) for op in "+-*/^" for a in _SMALL[:2] for b in _SMALL[:3]] + _SMALL
    u = Ref(name="u", kind="input")
    for x in inner:
        exprs = [Unary(arg=x)] if outer == "neg" else [Binary(op=outer, left=x, right=u),
                                                       Binary(op=outer, left=u, right=x)]
        for e in exprs:
            net = _expr_net(e)
            if net is not None:  # `u / (2 - 2)`: a division by zero
                round_trip(net)
