"""Emitters (`tnn_dsl.ir.emit`): equations, IR JSON, DOT.

The first half builds IR objects by hand (independent of the parser); the second half runs the
emitters over every network under networks/ (through `tnn_dsl.load`)."""

from __future__ import annotations

import glob
import os
import re

import numpy as np
import pytest

from tnn_dsl import Network
from tnn_dsl.ir import emit as _emit
from tnn_dsl.ir.network import (
    Binary,
    Boundary,
    Call,
    Fluid,
    Input,
    LearnFunction,
    LearnInput,
    LearnTarget,
    Link,
    Num,
    Param,
    Peltier,
    Radiation,
    Ref,
    Sensor,
    Source,
    Table,
    Temp,
    ThermalNode,
    Unary,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NETWORK_FILES = sorted(
    f for f in glob.glob(os.path.join(ROOT, "networks", "**", "*.thn"), recursive=True)
    if os.sep + "parts" + os.sep not in f
)

R_DIM = {"K": 1, "kg": -1, "m": -2, "s": 3}
G_DIM = {"kg": 1, "m": 2, "s": -3, "K": -1}
C_DIM = {"kg": 1, "m": 2, "s": -2, "K": -1}
W_DIM = {"kg": 1, "m": 2, "s": -3}
TK = {"K": 1}


# ---------------------------------------------------------------------------------------------
# Hand-built networks
# ---------------------------------------------------------------------------------------------


def _num(v, dim):
    return Num(value=v, dim=dim)


def case_study(learn: str = "linear", peltier_net: bool = False) -> Network:
    """The case-study network of thn-by-example.md §2 (M2 by default), built by hand."""
    params, nodes, links = [], [], []
    for n, c in dict(ph=40, pc=40, hs=600, hx1=300, hp=60, hx2=300, base=800).items():
        params.append(Param(name=f"C_{n}", expr=_num(c, C_DIM), dim=C_DIM, role="capacitance", owner=f"node {n}"))
        nodes.append(ThermalNode(name=n, capacitance=f"C_{n}"))
    params.append(Param(name="T_amb", expr=Ref(name="Ta", kind="input"), dim=TK, role="temperature"))
    for a, b, v, name in [("ph", "hs", 0.08, None), ("pc", "hx1", 0.05, None), ("hx1", "hp", 0.2, "R_hp1"),
                          ("hp", "hx2", 0.2, "R_hp2"), ("hp", "amb", 10, "R_hpa"), ("hs", "amb", 0.3, None),
                          ("base", "hs", 2, None), ("base", "hx1", 2, None), ("base", "amb", 3, None)]:
        name = name or f"R_{a}_{b}"
        params.append(Param(name=name, expr=_num(v, R_DIM), dim=R_DIM, role="resistance"))
        links.append(Link(name=name, a=a, b=b, form="R", value=name))
    vk = {"kg": 1, "m": 2, "s": -3, "A": -1, "K": -1}
    ohm = {"kg": 1, "m": 2, "s": -3, "A": -2}
    params += [
        Param(name="pe.current", expr=Ref(name="I", kind="input"), dim={"A": 1}, role="component"),
        Param(name="pe.seebeck", expr=_num(0.05, vk), dim=vk, role="component", free=True),
        Param(name="pe.resistance", expr=_num(2.0, ohm), dim=ohm, role="component", free=True),
        Param(name="pe.R_internal", expr=_num(1.5, R_DIM), dim=R_DIM, role="resistance"),
    ]
    fluids = []
    for f, node, tin in [("f1", "hx1", "Tf1"), ("f2", "hx2", "Tf2")]:
        params += [
            Param(name=f"{f}.inlet", expr=Ref(name=tin, kind="input"), dim=TK, role="temperature"),
            Param(name=f"{f}.mdot", expr=_num(0.002, {"kg": 1, "s": -1}), dim={"kg": 1, "s": -1}, role="component"),
            Param(name=f"{f}.cp", expr=_num(4186.0, {"m": 2, "s": -2, "K": -1}), dim={"m": 2, "s": -2, "K": -1},
                  role="component"),
            Param(name=f"{f}.UA", expr=_num(5.0, G_DIM), dim=G_DIM, role="conductance"),
        ]
        fluids.append(Fluid(name=f, node=node, inlet=f"{f}.inlet", mdot=f"{f}.mdot", cp=f"{f}.cp", ua=f"{f}.UA"))
    inputs = [Input(name="I", dim={"A": 1}, column="I"), Input(name="u1", column="u1")] + [
        Input(name=n, dim=TK, is_temperature=True, column=n) for n in ("Ta", "Tf1", "Tf2")
    ]
    learned = []
    if peltier_net:
        learned.append(LearnFunction(
            name="fn1", kind="mlp", hidden=[8, 8], replace=True, frozen=True,
            targets=[LearnTarget(kind="flow", name="pe.Q_hot"), LearnTarget(kind="flow", name="pe.Q_cold")],
            inputs=[LearnInput(kind="node", name="ph"), LearnInput(kind="node", name="pc"),
                    LearnInput(kind="input", name="I")]))
    if learn:
        learned.append(LearnFunction(
            name=f"fn{len(learned) + 1}", kind=learn, hidden=[8, 8] if learn == "mlp" else [],
            targets=[LearnTarget(kind="param", name=n) for n in ("R_hp1", "R_hp2", "R_hpa")],
            inputs=[] if learn == "const" else
            [LearnInput(kind="node", name=n) for n in ("hx1", "hp", "hx2")] + [LearnInput(kind="input", name="u1")]))
    return Network(
        name="peltier_heatpipe", label="Peltier cooler with heat pipe and two fluid heat exchangers",
        params=params, inputs=inputs, nodes=nodes, boundaries=[Boundary(name="amb", temperature="T_amb")],
        links=links,
        peltiers=[Peltier(name="pe", hot="ph", cold="pc", current="pe.current", seebeck="pe.seebeck",
                          resistance="pe.resistance", r_internal="pe.R_internal")],
        fluids=fluids, sensors=[Sensor(name="T_out", node="hx2", column="T_out")], learned=learned)


def tclab_lag() -> Network:
    """Two heaters with G links, a derived source, radiation, a lagged sensor with offset, a learned
    heat load, a numbered node and a table conductance."""
    params = [
        Param(name="Ta", expr=_num(296.15, TK), dim=TK, role="temperature", free=True, lower=288.15, upper=303.15),
        Param(name="a1", expr=_num(1.0, W_DIM), dim=W_DIM, free=True, lower=0.0, upper=5.0),
        Param(name="T_amb", expr=Ref(name="Ta", kind="param"), dim=TK, role="temperature"),
        Param(name="C_h1", expr=_num(4.0, C_DIM), dim=C_DIM, role="capacitance", free=True),
        Param(name="C_3", expr=_num(4.0, C_DIM), dim=C_DIM, role="capacitance"),
        Param(name="U1", expr=_num(0.05, G_DIM), dim=G_DIM, role="conductance", free=True),
        Param(name="U13", expr=Table(x=Call(fn="mean", args=[Temp(node="h1"), Temp(node="3")]),
                                     xs=[273.15, 323.15], ys=[0.02, 0.024], x_dim=TK, y_dim=G_DIM),
              dim=G_DIM, role="conductance"),
        Param(name="Q_src_h1",
              expr=Binary(op="*", left=Ref(name="a1", kind="param"), right=Ref(name="Q1", kind="input")),
              dim=W_DIM, role="heat_flow"),
        Param(name="rad_h1_amb.area", expr=_num(1e-3, {"m": 2}), dim={"m": 2}, role="component"),
        Param(name="rad_h1_amb.emissivity", expr=_num(0.9, {}), role="component", free=True),
        Param(name="rad_h1_amb.view_factor", expr=_num(1.0, {}), role="component"),
        Param(name="T1.lag", expr=_num(20.0, {"s": 1}), dim={"s": 1}, role="time_constant", free=True),
        Param(name="T1.offset", expr=_num(0.0, TK), dim=TK, role="offset", free=True),
    ]
    return Network(
        name="tclab_lag", label="TCLab with lag", params=params,
        inputs=[Input(name="Q1", column="Q1_pct", unit="%")],
        nodes=[ThermalNode(name="h1", capacitance="C_h1", label="heater 1"), ThermalNode(name="3", capacitance="C_3")],
        boundaries=[Boundary(name="amb", temperature="T_amb")],
        links=[Link(name="U1", a="h1", b="amb", form="G", value="U1"),
               Link(name="U13", a="h1", b="3", form="G", value="U13")],
        radiations=[Radiation(name="rad_h1_amb", a="h1", b="amb", area="rad_h1_amb.area",
                              emissivity="rad_h1_amb.emissivity", view_factor="rad_h1_amb.view_factor")],
        sources=[Source(name="Q_src_h1", node="h1", value="Q_src_h1")],
        sensors=[Sensor(name="T1", node="h1", column="T1_degC", lag="T1.lag", offset="T1.offset"),
                 Sensor(name="T3", node="3", column="T3_degC")],
        learned=[LearnFunction(name="fn1", kind="poly", degree=2, targets=[LearnTarget(kind="heat_load", name="3")],
                               inputs=[LearnInput(kind="node", name="3"), LearnInput(kind="input", name="Q1")])],
    )


# ---------------------------------------------------------------------------------------------
# Units and expressions
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dim,text", [
    (R_DIM, "K/W"), (G_DIM, "W/K"), (C_DIM, "J/K"), (W_DIM, "W"), ({}, "1"), ({"s": 1}, "s"),
    ({"m": 2, "s": -2, "K": -1}, "J/(kg·K)"), ({"kg": 1, "m": 2, "s": -3, "A": -2}, "ohm"),
    ({"kg": 1, "m": 3}, "kg·m³"), ({"m": 1, "s": -2, "A": -1, "K": -1}, "m/(s²·K·A)"),
])
def test_format_dim(dim, text):
    assert _emit.format_dim(dim) == text


def test_format_dim_ascii():
    assert _emit.format_dim({"kg": 1, "m": 3}, ascii_only=True) == "kg*m^3"
    assert _emit.format_dim({"m": 2, "s": -2, "K": -1}, ascii_only=True) == "J/(kg*K)"


def test_format_quantity():
    assert _emit.format_quantity(0.2, R_DIM) == "0.2 K/W"
    assert _emit.format_quantity(1e-3, {"m": 2}) == "0.001 m²"
    assert _emit.format_quantity(5.670374419e-8, {}) == "5.67037e-8"
    assert _emit.format_quantity(1.5, {}) == "1.5"


def _r(name):
    return Ref(name=name, kind="param")


@pytest.mark.parametrize("expr,text", [
    (Binary(op="-", left=_r("a"), right=Binary(op="-", left=_r("b"), right=_r("c"))), "a − (b − c)"),
    (Binary(op="-", left=Binary(op="-", left=_r("a"), right=_r("b")), right=_r("c")), "a − b − c"),
    (Binary(op="*", left=Binary(op="+", left=_r("a"), right=_r("b")), right=_r("c")), "(a + b)·c"),
    (Binary(op="/", left=_r("a"), right=Binary(op="*", left=_r("b"), right=_r("c"))), "a/(b·c)"),
    (Binary(op="*", left=Binary(op="/", left=_r("a"), right=_r("b")), right=_r("c")), "a/b·c"),
    (Unary(arg=Binary(op="^", left=_r("x"), right=_num(2.0, {}))), "−x^2"),
    (Binary(op="^", left=Unary(arg=_r("x")), right=_num(2.0, {})), "(−x)^2"),
    (Binary(op="^", left=_r("a"), right=Binary(op="^", left=_r("b"), right=_r("c"))), "a^b^c"),
    (Binary(op="^", left=Binary(op="^", left=_r("a"), right=_r("b")), right=_r("c")), "(a^b)^c"),
    (Binary(op="*", left=_num(0.2, R_DIM), right=Binary(op="+", left=_num(1.0, {}), right=_r("u"))),
     "(0.2 K/W)·(1 + u)"),
    (Call(fn="mean", args=[Temp(node="hx1"), Temp(node="3")]), "mean(T_hx1, T3)"),
    (Binary(op="+", left=_r("a"), right=_num(-2.0, {})), "a + (-2)"),
])
def test_expressions_bracket_exactly_where_needed(expr, text):
    net = Network(name="x", params=[Param(name=n, expr=_num(1.0, {})) for n in "abcux"])
    assert _emit.format_expr(net, expr) == text


# ---------------------------------------------------------------------------------------------
# Equations
# ---------------------------------------------------------------------------------------------


def _eq_line(text: str, node: str) -> str:
    sym = f"T{node}" if node[:1].isdigit() else f"T_{node}"
    lines = [ln for ln in text.splitlines() if re.match(rf"^\S+·d{re.escape(sym)}/dt = ", ln)]
    assert len(lines) == 1, text
    return lines[0]


def test_case_study_equations_have_every_term():
    text = _emit.equations(case_study("linear"))
    hx2 = _eq_line(text, "hx2")
    assert hx2 == ("C_hx2·dT_hx2/dt = (T_hp − T_hx2)/R_hp2(hx1, hp, hx2, u1) "
                   "+ f2.mdot·f2.cp·(1 − a_f2)·(Tf2 − T_hx2)")
    hp = _eq_line(text, "hp")
    for term in ("(T_hx1 − T_hp)/R_hp1(hx1, hp, hx2, u1)", "(T_hx2 − T_hp)/R_hp2(hx1, hp, hx2, u1)",
                 "(T_amb − T_hp)/R_hpa(hx1, hp, hx2, u1)"):
        assert term in hp
    ph = _eq_line(text, "ph")
    assert "(pe.seebeck·T_ph·I + ½·pe.resistance·I²)" in ph
    assert "(T_pc − T_ph)/pe.R_internal" in ph
    assert "(T_hs − T_ph)/R_ph_hs" in ph
    pc = _eq_line(text, "pc")
    assert "(−pe.seebeck·T_pc·I + ½·pe.resistance·I²)" in pc
    assert "(T_ph − T_pc)/pe.R_internal" in pc
    assert "a_f2 = exp(−f2.UA/(f2.mdot·f2.cp))" in text
    assert "T_out = T_hx2" in text
    # learned resistances: positive by construction, nominal untrained
    assert "R_hp1(hx1, hp, hx2, u1) = 0.2 K/W·pos1(1 + z₁(hx1, hp, hx2, u1))" in text
    assert "R_hpa(hx1, hp, hx2, u1) = 10 K/W·pos1(1 + z₃(hx1, hp, hx2, u1))" in text
    assert "positive by construction" in text
    assert "fn1 = linear(hx1, hp, hx2, u1) → R_hp1, R_hp2, R_hpa" in text
    assert "pe.seebeck = 0.05 V/K   (free)" in text
    assert "C_base = 800 J/K   (positive)" in text
    assert "f1.inlet = Tf1   (input, K)" in text


def test_every_link_appears_at_both_ends():
    net = case_study("const")
    text = _emit.equations(net)
    for link in net.links:
        a = f"T{link.a}" if link.a[:1].isdigit() else f"T_{link.a}"
        b = f"T{link.b}" if link.b[:1].isdigit() else f"T_{link.b}"
        sym = link.value
        for me, other, node in ((a, b, link.a), (b, a, link.b)):
            if node == "amb":
                continue
            assert f"({other} − {me})/{sym}" in _eq_line(text, node)
    assert "fn1 = const → R_hp1, R_hp2, R_hpa" in text
    assert "R_hp2 = 0.2 K/W·pos1(1 + z₂)   positive by construction" in text


def test_replaced_peltier_flows_are_functions_of_their_inputs():
    text = _emit.equations(case_study("mlp", peltier_net=True))
    ph, pc = _eq_line(text, "ph"), _eq_line(text, "pc")
    assert "pe.Q_hot(ph, pc, I)" in ph and "seebeck" not in ph
    assert "pe.Q_cold(ph, pc, I)" in pc and "seebeck" not in pc
    assert "(T_pc − T_ph)/pe.R_internal" in ph          # the internal conduction stays physical
    assert "replaces the physics flow of pe" in text
    assert "fn1 = mlp(ph, pc, I; hidden = [8, 8], activation = tanh, replace) → pe.Q_hot, pe.Q_cold   [frozen]" in text
    assert "fn2 = mlp(hx1, hp, hx2, u1; hidden = [8, 8], activation = tanh) → R_hp1, R_hp2, R_hpa" in text


def test_correcting_flow_keeps_physics():
    net = case_study("")
    net.learned.append(LearnFunction(name="fn1", kind="linear", targets=[LearnTarget(kind="flow", name="f1.Q")],
                                     inputs=[LearnInput(kind="input", name="u1")]))
    text = _emit.equations(net)
    assert "f1.Q(u1)" in _eq_line(text, "hx1")
    assert "f1.Q_physics = f1.mdot·f1.cp·(1 − a_f1)·(Tf1 − T_hx1)" in text
    assert "correction to the physics flow of f1" in text


def test_g_links_radiation_sources_lag_heat_load_numbered_nodes():
    text = _emit.equations(tclab_lag())
    h1 = _eq_line(text, "h1")
    assert h1.startswith("C_h1·dT_h1/dt = ")
    assert "U1·(T_amb − T_h1)" in h1
    assert "U13·(T3 − T_h1)" in h1
    assert "σ·rad_h1_amb.area·rad_h1_amb.emissivity·rad_h1_amb.view_factor·(T_amb⁴ − T_h1⁴)" in h1
    assert h1.endswith("+ Q_src_h1   # heater 1")
    n3 = _eq_line(text, "3")
    assert n3 == "C_3·dT3/dt = U13·(T_h1 − T3) + Q[3](T3, Q1)"
    assert "T1.lag·dTs_T1/dt = T_h1 − Ts_T1   # sensor T1: first-order lag state" in text
    assert 'T1 = Ts_T1 + T1.offset   (column "T1_degC")' in text
    assert 'T3 = T3   (column "T3_degC")' in text
    assert "Q_src_h1 = a1·Q1   (derived, W)" in text
    assert "T_amb = Ta   (derived, K)" in text
    assert "U13 = table(mean(T_h1, T3); 273.15 K: 0.02 W/K, 323.15 K: 0.024 W/K)" in text
    assert "Ta = 296.15 K   (free in [288.15, 303.15] K)" in text
    assert "Q[3](T3, Q1) = y_scale·z₁(T3, Q1)" in text and "0 W untrained" in text
    assert "σ = 5.67037e-08" in text or "σ = 5.67037e-8" in text


def test_ascii_equations_are_ascii():
    for net in (case_study("mlp", peltier_net=True), tclab_lag()):
        text = _emit.equations(net, ascii_only=True)
        assert text.isascii(), [c for c in text if not c.isascii()]
        assert "C_hx2*dT_hx2/dt" in text or "C_h1*dT_h1/dt" in text


def test_empty_node_equation_reads_zero():
    net = Network(name="lonely", params=[Param(name="C_a", expr=_num(1.0, C_DIM), dim=C_DIM, role="capacitance")],
                  nodes=[ThermalNode(name="a", capacitance="C_a")])
    assert "C_a·dT_a/dt = 0" in _emit.equations(net)


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("make", [lambda: case_study("linear"), lambda: case_study("mlp", True), tclab_lag])
def test_json_round_trip_hand_built(make):
    net = make()
    text = _emit.ir_json(net)
    back = Network.from_json(text)
    assert back == net
    assert _emit.ir_json(back) == text


def test_bad_json_is_a_tnn_error():
    from tnn_dsl import TnnError

    with pytest.raises(TnnError) as err:
        _emit.network_from_json('{"name": 3, "nodes": "x"}', "bad.json")
    assert "bad.json: not a tnn_dsl IR file" in str(err.value)
    with pytest.raises(TnnError):
        _emit.network_from_json("not json at all", "bad.json")


# ---------------------------------------------------------------------------------------------
# DOT
# ---------------------------------------------------------------------------------------------

_DOT_STMT = re.compile(
    r'^  (graph|node|edge) \[.*\];$'
    r'|^  "(?:[^"\\]|\\.)*" \[.*\];$'
    r'|^  "(?:[^"\\]|\\.)*" -> "(?:[^"\\]|\\.)*" \[.*\];$'
)


def _check_dot_syntax(text: str) -> None:
    lines = text.rstrip("\n").split("\n")
    assert re.match(r'^digraph "(?:[^"\\]|\\.)*" \{$', lines[0])
    assert lines[-1] == "}"
    for ln in lines[1:-1]:
        assert _DOT_STMT.match(ln), ln
        # quotes balance once escapes are removed
        assert ln.replace('\\"', "").count('"') % 2 == 0, ln


def test_dot_has_every_vertex_and_edge_and_highlights_learning():
    net = case_study("linear")
    text = _emit.dot(net)
    _check_dot_syntax(text)
    for v in net.node_names + net.boundary_names + ["f1.inlet", "f2.inlet", "sensor:T_out"]:
        assert f'  "{v}" [' in text, v
    for link in net.links:
        assert f'"{link.a}" -> "{link.b}"' in text
    learned = [ln for ln in text.splitlines() if '"hx1" -> "hp"' in ln][0]
    assert "R_hp1 ~ linear(hx1, hp, hx2, u1)" in learned and "#d62728" in learned
    plain = [ln for ln in text.splitlines() if '"ph" -> "hs"' in ln][0]
    assert "R_ph_hs = 0.08 K/W" in plain and "#d62728" not in plain
    assert '"pc" -> "ph"' in text and "Peltier pe" in text
    assert '"f2.inlet" -> "hx2"' in text


def test_dot_sources_heat_loads_radiation_sensor_lag():
    text = _emit.dot(tclab_lag())
    _check_dot_syntax(text)
    assert '"source:Q_src_h1" -> "h1"' in text
    assert '"heat_load:3" -> "3"' in text and "Q[3] ~ poly(T3, Q1)" in text
    rad = [ln for ln in text.splitlines() if "radiation rad_h1_amb" in ln][0]
    assert "style=dashed" in rad and "rad_h1_amb.emissivity = 0.9 (free)" in rad
    assert "T1.lag = 20 s (free)" in text


def test_dot_escapes_quotes_in_labels():
    net = case_study("")
    net.nodes[0] = ThermalNode(name="ph", capacitance="C_ph", label='the "hot" side\\')
    text = _emit.dot(net)
    _check_dot_syntax(text)
    assert r'the \"hot\" side\\' in text


def test_png_without_graphviz_uses_matplotlib(tmp_path, monkeypatch):
    import tnn_dsl.plots.drawing as drawing

    monkeypatch.setattr(drawing.shutil, "which", lambda name: None)
    out = tmp_path / "net.png"
    how = drawing.render_png(case_study("linear"), str(out), dpi=40)
    assert how == "matplotlib"
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------
# Every network under networks/
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("path", NETWORK_FILES, ids=lambda p: os.path.relpath(p, ROOT))
def test_every_network_emits(path):
    import tnn_dsl

    net = tnn_dsl.load(path)
    text = _emit.ir_json(net)
    back = Network.from_json(text)
    assert back == net
    assert _emit.ir_json(back) == text
    eqs = _emit.equations(net)
    for n in net.nodes:
        _eq_line(eqs, n.name)
    d = _emit.dot(net)
    _check_dot_syntax(d)
    for v in net.node_names + net.boundary_names:
        assert f'  "{v}" [' in d
    assert d.count(" -> ") >= len(net.links) + len(net.radiations) + len(net.peltiers) + len(net.fluids)
    assert _emit.equations(net, ascii_only=True).isascii()


# ---------------------------------------------------------------------------------------------
# The printed equations are the model: evaluate the ASCII text and compare with the compiled rhs
# ---------------------------------------------------------------------------------------------

_TOKEN = re.compile(r"\s*(?:(\d+\.?\d*(?:e[+-]?\d+)?)|(Q\[[^\]]+\]|[A-Za-z_][A-Za-z0-9_.]*)|(.))")
_FUNCS = {
    "exp": lambda *a: np.exp(a[0]), "log": lambda *a: np.log(a[0]), "sqrt": lambda *a: np.sqrt(a[0]),
    "abs": lambda *a: abs(a[0]), "min": lambda *a: min(a), "max": lambda *a: max(a),
    "mean": lambda *a: sum(a) / len(a), "series": lambda *a: sum(a),
    "parallel": lambda *a: 1.0 / sum(1.0 / x for x in a),
}


class _TextEval:
    """A tiny recursive-descent evaluator for the ASCII equations `tnnc compile` prints (no eval)."""

    def __init__(self, lookup, call):
        self.lookup, self.call = lookup, call

    def __call__(self, text: str) -> float:
        self.toks = [(m.group(1), m.group(2), m.group(3)) for m in _TOKEN.finditer(text) if m.group(0).strip()]
        self.i = 0
        v = self.sum()
        assert self.i == len(self.toks), (text, self.toks[self.i:])
        return v

    def peek(self, ch):
        return self.i < len(self.toks) and self.toks[self.i][2] == ch

    def take(self, ch):
        assert self.peek(ch), (ch, self.toks[self.i:])
        self.i += 1

    def sum(self):
        v = self.prod()
        while self.peek("+") or self.peek("-"):
            op = self.toks[self.i][2]
            self.i += 1
            w = self.prod()
            v = v + w if op == "+" else v - w
        return v

    def prod(self):
        v = self.unary()
        while self.peek("*") or self.peek("/"):
            op = self.toks[self.i][2]
            self.i += 1
            w = self.unary()
            v = v * w if op == "*" else v / w
        return v

    def unary(self):
        if self.peek("-"):
            self.i += 1
            return -self.unary()
        return self.power()

    def power(self):
        v = self.atom()
        if self.peek("^"):
            self.i += 1
            return v ** self.unary()
        return v

    def atom(self):
        num, name, ch = self.toks[self.i]
        self.i += 1
        if num is not None:
            return float(num)
        if ch == "(":
            v = self.sum()
            self.take(")")
            return v
        assert name is not None, (ch, self.toks)
        if self.peek("("):
            self.i += 1
            args = []
            if not self.peek(")"):
                args.append(self.sum() if name in _FUNCS else self._arg())
                while self.peek(","):
                    self.i += 1
                    args.append(self.sum() if name in _FUNCS else self._arg())
            self.take(")")
            return _FUNCS[name](*args) if name in _FUNCS else self.call(name)
        return self.lookup(name)

    def _arg(self):  # arguments of a learned function are names; the untrained function ignores them
        self.i += 1
        return None


def _rhs_from_text(net, text, T, u):
    """dT/dt (K/s) for every state, computed from the printed equations alone (plus parameter values)."""
    from tnn_dsl.compiler.expressions import evaluate

    nodes = {(f"T{n.name}" if n.name[:1].isdigit() else f"T_{n.name}"): i for i, n in enumerate(net.nodes)}
    lagged = [s for s in net.sensors if s.lag]
    states = {**nodes, **{f"Ts_{s.name}": len(net.nodes) + k for k, s in enumerate(lagged)}}
    temps = {n.name: T[i] for i, n in enumerate(net.nodes)}
    inputs = {i.name: u[k] for k, i in enumerate(net.inputs)}
    params = {p.name: p for p in net.params}
    cache: dict[str, float] = {}

    def pvalue(name):
        if name not in cache:
            e = params[name].expr
            if isinstance(e, Num):
                cache[name] = e.value
            else:
                from tnn_dsl.compiler.expressions import dependencies

                refs, nodes_read = dependencies(e)
                vals = {r: (inputs[r] if r in inputs else pvalue(r)) for r in refs}
                bnd = {b.name: pvalue(b.temperature) for b in net.boundaries if b.name in nodes_read}
                cache[name] = float(evaluate(e, np, vals, {**temps, **bnd}))
        return cache[name]

    defs = {}
    section = None
    for line in text.splitlines():
        if not line.startswith("  "):
            section = line
            continue
        if section == "component flows":
            lhs, rhs = line.strip().split(" = ", 1)
            defs[lhs] = rhs.split("   (")[0]
    targets = net.learned_targets()
    boundary_sym = {(f"T{b.name}" if b.name[:1].isdigit() else f"T_{b.name}"): b.temperature for b in net.boundaries}

    def lookup(name):
        if name in states:
            return T[states[name]]
        if name in boundary_sym:
            return pvalue(boundary_sym[name])
        if name == "sigma":
            return _emit.SIGMA
        if name in defs:
            return ev(defs[name])
        if name in inputs:
            return inputs[name]
        return pvalue(name)

    def call(name):
        if name.startswith("Q["):
            return 0.0                                  # untrained heat load
        fn, _ = targets[name]
        if name in params:
            return pvalue(name)                         # untrained: the nominal value
        return 0.0 if fn.replace else ev(defs[f"{name}_physics"])

    def ev(expr_text):  # a fresh evaluator per call: definitions are evaluated inside other lines
        return _TextEval(lookup, call)(expr_text)

    out = np.zeros(len(states))
    for line in text.splitlines():
        m = re.match(r"^(\S+)\*d(\S+)/dt = (.*?)(?:   # .*)?$", line)
        if not m:
            continue
        cap, state, rhs = m.groups()
        cap_val = ev(cap)
        out[states[state]] = ev(rhs) / cap_val
    return out


@pytest.mark.parametrize("backend", ["jax", "torch"])
@pytest.mark.parametrize("path", NETWORK_FILES, ids=lambda p: os.path.relpath(p, ROOT))
def test_printed_equations_agree_with_the_compiled_model(path, backend):
    import tnn_dsl

    net = tnn_dsl.load(path)
    text = _emit.equations(net, ascii_only=True)
    model = tnn_dsl.compile(net, backend=backend, dtype="float64")
    params = model.init_params(seed=0)
    rng = np.random.default_rng(7)
    for _ in range(3):
        T = 290.0 + 40.0 * rng.random(len(model.state_names))
        u = np.array([285.0 + 20.0 * rng.random() if i.is_temperature else rng.random() * 3.0 for i in net.inputs])
        want = np.asarray(model.to_numpy({"dT": model.rhs(params, _arr(backend, T), _arr(backend, u))})["dT"])
        got = _rhs_from_text(net, text, T, u)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)


def _arr(backend, x):
    if backend == "torch":
        import torch

        return torch.tensor(x, dtype=torch.float64)
    import jax.numpy as jnp

    return jnp.asarray(x, dtype=jnp.float64)
