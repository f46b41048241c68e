"""The networks library (networks/): every file loads, and says what its comments say it does.

Values are checked in SI (kelvin, J/K, K/W, W/K, W, s) against ../shared/spec/case-study.md, the spec's
TCLab example and the building starting values written in the files' headers."""

from __future__ import annotations

import csv
import glob
import math
import os

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.ir.network import Num

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NET = os.path.join(ROOT, "networks")
DATA = os.path.join(os.path.dirname(ROOT), "shared", "data")
ALL = sorted(glob.glob(os.path.join(NET, "**", "*.thn"), recursive=True))
KWH = 3.6e6  # J per kWh
C0 = 273.15


def load(rel: str):
    return tnn_dsl.load(os.path.join(NET, rel))


def value(net, name: str) -> float:
    p = net.param(name)
    assert isinstance(p.expr, Num), f"{name} is not a constant"
    return p.expr.value


def test_the_library_is_complete():
    names = {os.path.relpath(p, NET) for p in ALL}
    expected = {
        "tclab/tclab.thn", "tclab/tclab_lag.thn",
        *(f"peltier_heatpipe/{m}.thn" for m in ("m1", "m2", "m3", "m4", "m5", "nominal", "truth")),
        "building/ti.thn", "building/tite.thn", "building/tith.thn", "building/titeth.thn",
        "box/box3.thn", "examples/tclab_include.thn", "examples/two_rooms_subnet.thn",
    }
    assert expected <= names


@pytest.mark.parametrize("path", ALL, ids=lambda p: os.path.relpath(p, NET))
def test_every_network_loads_and_says_where_it_comes_from(path):
    net = tnn_dsl.load(path)
    assert net.nodes and net.sensors
    with open(path, encoding="utf-8") as f:
        first = f.readline()
    assert first.startswith("# "), (
        "each file opens with a comment saying what it models and where its numbers come from")


@pytest.mark.parametrize("path", ALL, ids=lambda p: os.path.relpath(p, NET))
def test_every_network_has_a_path_to_a_boundary(path):
    """No floating node: every thermal node reaches a boundary or a fluid inlet (steady state exists)."""
    import networkx as nx

    net = tnn_dsl.load(path)
    g = net.graph()
    anchors = [v for v, d in g.nodes(data=True) if d["kind"] in ("boundary", "fluid_inlet")]
    assert anchors
    for n in net.node_names:
        assert any(nx.has_path(g, n, a) for a in anchors), n


# -- TCLab ----------------------------------------------------------------------------------


def test_tclab_is_the_spec_example():
    net = load("tclab/tclab.thn")
    assert net.name == "tclab" and net.temperature_unit == "degC"
    assert net.node_names == ["h1", "h2"] and net.boundary_names == ["amb"]
    assert [(i.name, i.column) for i in net.inputs] == [("Q1", "Q1_pct"), ("Q2", "Q2_pct")]
    ta = net.param("Ta")
    assert ta.free and ta.expr.value == pytest.approx(23 + C0)
    assert (ta.lower, ta.upper) == (pytest.approx(15 + C0), pytest.approx(30 + C0))
    assert value(net, "a1") == pytest.approx(1.0)    # 0.01 W/% = 1 W per unit fraction
    assert value(net, "a2") == pytest.approx(0.75)
    assert value(net, "C_h1") == 4.0 and net.param("C_h1").free
    assert {l.name: (l.form, l.a, l.b) for l in net.links} == {
        "U1": ("G", "h1", "amb"), "U2": ("G", "h2", "amb"), "U12": ("G", "h1", "h2")}
    assert value(net, "U12") == pytest.approx(0.02)
    assert sorted(p.name for p in net.free_params) == sorted(["Ta", "a1", "a2", "C_h1", "C_h2", "U1", "U2", "U12"])
    assert [(s.name, s.node, s.column, s.lag) for s in net.sensors] == [
        ("T1", "h1", "T1_degC", None), ("T2", "h2", "T2_degC", None)]
    assert [s.node for s in net.sources] == ["h1", "h2"]
    assert not net.learned


def test_tclab_lag_adds_lags_and_radiation():
    base, net = load("tclab/tclab.thn"), load("tclab/tclab_lag.thn")
    assert net.node_names == base.node_names
    assert [(r.a, r.b) for r in net.radiations] == [("h1", "amb"), ("h2", "amb"), ("h1", "h2")]
    assert value(net, f"{net.radiations[0].name}.area") == pytest.approx(1e-3)
    assert value(net, f"{net.radiations[2].name}.area") == pytest.approx(2e-4)
    em = net.param(net.radiations[0].emissivity)
    assert em.free and em.expr.value == pytest.approx(0.9)
    for s in net.sensors:
        lag = net.param(s.lag)
        assert lag.free and lag.expr.value == 20.0 and (lag.lower, lag.upper) == (1.0, 600.0)


@pytest.mark.parametrize("rel,data", [
    ("tclab/tclab.thn", "tclab_kuntz_rawlings_prbs_openloop.csv"),
    ("tclab/tclab.thn", "tclab_apmonitor_energy_balance_steps.csv"),
    ("tclab/tclab_lag.thn", "tclab_kuntz_rawlings_prbs_openloop.csv"),
    ("examples/tclab_include.thn", "tclab_kuntz_rawlings_prbs_openloop.csv"),
    ("building/ti.thn", "bacher_madsen_inputPRBS1.csv"),
    ("building/tite.thn", "bacher_madsen_inputPRBS1.csv"),
    ("building/tith.thn", "bacher_madsen_inputPRBS1.csv"),
    ("building/titeth.thn", "bacher_madsen_inputPRBS1.csv"),
])
def test_columns_exist_in_the_real_data(rel, data):
    path = os.path.join(DATA, data)
    if not os.path.exists(path):
        pytest.skip(f"{path} is not available")
    with open(path, newline="", encoding="utf-8") as f:
        header = next(csv.reader(f))
    net = load(rel)
    for col in [i.column for i in net.inputs] + [s.column for s in net.sensors]:
        assert col in header, (col, header)


# -- The case study -------------------------------------------------------------------------

CASE = ["m1", "m2", "m3", "m4", "m5", "nominal", "truth"]


@pytest.mark.parametrize("m", CASE)
def test_case_study_structure_and_values(m):
    net = load(f"peltier_heatpipe/{m}.thn")
    assert net.node_names == ["ph", "pc", "hs", "hx1", "hp", "hx2", "base"]
    assert net.boundary_names == ["amb"]
    assert [i.name for i in net.inputs] == ["I", "u1", "Ta", "Tf1", "Tf2"]
    assert [i.is_temperature for i in net.inputs] == [False, False, True, True, True]
    caps = dict(ph=40, pc=40, hs=600, hx1=300, hp=60, hx2=300, base=800)
    for n in net.nodes:
        assert value(net, n.capacitance) == caps[n.name]
    ends = {frozenset((l.a, l.b)): l for l in net.links}
    fixed = {("ph", "hs"): 0.08, ("pc", "hx1"): 0.05, ("hs", "amb"): 0.3, ("base", "hs"): 2,
             ("base", "hx1"): 2, ("base", "amb"): 3}
    assert len(net.links) == 9
    for (a, b), r in fixed.items():
        link = ends[frozenset((a, b))]
        assert link.form == "R" and value(net, link.value) == pytest.approx(r)
    for (a, b), name in {("hx1", "hp"): "R_hp1", ("hp", "hx2"): "R_hp2", ("hp", "amb"): "R_hpa"}.items():
        assert ends[frozenset((a, b))].value == name
    (pe,) = net.peltiers
    assert (pe.hot, pe.cold) == ("ph", "pc")
    assert value(net, pe.seebeck) == pytest.approx(0.05)
    assert value(net, pe.resistance) == pytest.approx(2.0)
    assert value(net, pe.r_internal) == pytest.approx(1.5)
    assert [f.node for f in net.fluids] == ["hx1", "hx2"]
    for f in net.fluids:
        assert value(net, f.mdot) == pytest.approx(0.002)
        assert value(net, f.cp) == pytest.approx(4186)
        assert value(net, f.ua) == pytest.approx(5)
    assert [(s.name, s.node, s.column) for s in net.sensors] == [("T_out", "hx2", "T_out")]
    if m in ("m1", "m2", "m3", "nominal"):
        assert {p.name for p in net.free_params} == {pe.seebeck, pe.resistance}
    else:  # the flows are a net (m4, m5) or the truth: nothing to fit in the Peltier equation
        assert not net.free_params


@pytest.mark.parametrize("m", ["m1", "m2", "m3", "m4", "nominal"])
def test_nominal_heat_pipe(m):
    net = load(f"peltier_heatpipe/{m}.thn")
    assert value(net, "R_hp1") == value(net, "R_hp2") == pytest.approx(0.2)
    assert value(net, "R_hpa") == pytest.approx(10.0)


def _targets(fn):
    return [t.name for t in fn.targets]


def test_case_study_learn_lines():
    hp = ["R_hp1", "R_hp2", "R_hpa"]
    hp_in = [("node", "hx1"), ("node", "hp"), ("node", "hx2"), ("input", "u1")]
    (f,) = load("peltier_heatpipe/m1.thn").learned
    assert (f.kind, _targets(f), f.inputs) == ("const", hp, [])
    (f,) = load("peltier_heatpipe/m2.thn").learned
    assert (f.kind, _targets(f), [(i.kind, i.name) for i in f.inputs]) == ("linear", hp, hp_in)
    (f,) = load("peltier_heatpipe/m3.thn").learned
    assert (f.kind, _targets(f), f.hidden, f.activation) == ("mlp", hp, [8, 8], "sigmoid")
    assert [(i.kind, i.name) for i in f.inputs] == hp_in
    pel, const = load("peltier_heatpipe/m4.thn").learned
    assert (pel.kind, _targets(pel), pel.hidden, pel.replace, pel.frozen) == (
        "mlp", ["pe.Q_hot", "pe.Q_cold"], [8, 8], True, False)
    assert [t.kind for t in pel.targets] == ["flow", "flow"]
    assert [(i.kind, i.name) for i in pel.inputs] == [("node", "ph"), ("node", "pc"), ("input", "I")]
    assert (const.kind, _targets(const)) == ("const", hp)
    pel5, hp5 = load("peltier_heatpipe/m5.thn").learned
    assert (pel5.kind, _targets(pel5), pel5.hidden, pel5.replace, pel5.frozen) == (
        "mlp", ["pe.Q_hot", "pe.Q_cold"], [8, 8], True, True)
    assert pel5.name == pel.name                      # the same function name as in M4
    assert pel5.init_from and pel5.init_from.replace(os.sep, "/").endswith("peltier_heatpipe/models/m4")
    assert (hp5.kind, _targets(hp5), hp5.hidden, hp5.activation, hp5.frozen) == ("mlp", hp, [8, 8], "sigmoid", False)
    assert not load("peltier_heatpipe/nominal.thn").learned
    assert not load("peltier_heatpipe/truth.thn").learned


def test_the_models_differ_from_the_nominal_only_in_learn_lines():
    nominal = load("peltier_heatpipe/nominal.thn")
    strip = lambda net, fields: net.model_dump(include=fields)  # noqa: E731
    fields = {"nodes", "boundaries", "links", "radiations", "fluids", "sources", "sensors", "inputs"}

    def no_spans(x):
        if isinstance(x, dict):
            return {k: no_spans(v) for k, v in x.items() if k != "span"}
        if isinstance(x, list):
            return [no_spans(v) for v in x]
        return x

    ref = no_spans(strip(nominal, fields))
    for m in ("m1", "m2", "m3", "m4", "m5"):
        net = load(f"peltier_heatpipe/{m}.thn")
        assert no_spans(strip(net, fields)) == ref, m
        assert [p.name for p in net.params] == [p.name for p in nominal.params]


def _truth_resistances(u1, t_hx1, t_hp, t_hx2):
    """case-study.md, written independently of the .thn file."""
    r1 = 0.2 * (1 + 1.5 * (u1 - 0.5) - 0.02 * ((t_hx1 + t_hp) / 2 - (25 + C0)))
    r2 = 0.2 * (1 + 1.2 * (u1 - 0.5) - 0.02 * ((t_hp + t_hx2) / 2 - (25 + C0)))
    ra = 10 * (1 + 0.3 * (u1 - 0.5))
    return r1, r2, ra


@pytest.mark.parametrize("u1,temps", [
    (0.5, (25, 25, 25)), (1.0, (25, 25, 25)), (0.0, (35, 30, 28)), (0.73, (12.5, 19, 40)), (1.4, (60, 50, 45)),
])
def test_truth_heat_pipe_matches_the_case_study(u1, temps):
    from tnn_dsl.compiler.expressions import evaluate

    net = load("peltier_heatpipe/truth.thn")
    t = dict(zip(("hx1", "hp", "hx2"), (x + C0 for x in temps)))
    values = {p.name: p.expr.value for p in net.params if isinstance(p.expr, Num)}
    values["u1"] = u1
    got = [float(evaluate(net.param(n).expr, np, values, t)) for n in ("R_hp1", "R_hp2", "R_hpa")]
    assert got == pytest.approx(_truth_resistances(u1, *t.values()), rel=1e-12)
    for n in ("R_hp1", "R_hp2", "R_hpa"):
        assert net.param(n).role == "resistance"


# -- Buildings ------------------------------------------------------------------------------


def test_building_ti():
    net = load("building/ti.thn")
    assert net.node_names == ["ti"] and net.boundary_names == ["amb"]
    assert value(net, "C_ti") == pytest.approx(2.9 * KWH)
    assert value(net, "Ria") == pytest.approx(5.4e-3)           # 5.4 K/kW
    assert value(net, "Aw") == pytest.approx(11.0)
    ps = next(i for i in net.inputs if i.name == "Ps")
    ph = next(i for i in net.inputs if i.name == "Ph")
    assert ps.dim == {"kg": 1.0, "s": -3.0} and ph.dim == {"kg": 1.0, "m": 2.0, "s": -3.0}
    assert next(i for i in net.inputs if i.name == "Ta").is_temperature
    assert {s.name: s.node for s in net.sources} == {"Q_solar": "ti", "Q_heat": "ti"}
    assert [(s.name, s.column) for s in net.sensors] == [("Ti", "yTi")]
    assert {p.name for p in net.free_params} == {"Aw", "C_ti", "Ria"}


@pytest.mark.parametrize("rel,nodes,links,heater_node", [
    ("building/tite.thn", ["ti", "te"], {("ti", "te"): ("Rie", 2.1e-3), ("te", "amb"): ("Rea", 3.4e-3)}, "ti"),
    ("building/tith.thn", ["ti", "th"], {("th", "ti"): ("Rih", 0.5e-3), ("ti", "amb"): ("Ria", 5.4e-3)}, "th"),
    ("building/titeth.thn", ["ti", "te", "th"],
     {("th", "ti"): ("Rih", 0.5e-3), ("ti", "te"): ("Rie", 2.1e-3), ("te", "amb"): ("Rea", 3.4e-3)}, "th"),
])
def test_building_extensions(rel, nodes, links, heater_node):
    net = load(rel)
    assert net.node_names == nodes
    got = {(l.a, l.b): (l.name, value(net, l.value)) for l in net.links}
    assert set(got) == set(links)
    for k, (name, v) in links.items():
        assert got[k][0] == name and got[k][1] == pytest.approx(v, rel=1e-12)
    src = {s.name: s.node for s in net.sources}
    assert src == {"Q_solar": "ti", "Q_heat": heater_node}
    assert all(p.free for p in net.params if p.role in ("capacitance", "resistance"))
    # time constants are physical: minutes to days
    for n in net.nodes:
        c = value(net, n.capacitance)
        r = min(value(net, l.value) for l in net.links if n.name in (l.a, l.b))
        assert 60 < c * r < 30 * 86400, (n.name, c * r)


# -- Box and examples -----------------------------------------------------------------------


def test_box3_design_card():
    net = load("box/box3.thn")
    assert net.node_names == ["2", "3", "4"]
    assert [n.capacitance for n in net.nodes] == ["C_2", "C_3", "C_4"]
    assert value(net, "C_3") == 300 and value(net, "R_hp") == pytest.approx(0.2)
    link = next(l for l in net.links if l.value == "R_hp")
    assert (link.a, link.b) == ("3", "4")
    (fn,) = net.learned
    assert (fn.kind, _targets(fn)) == ("mlp", ["R_hp"])
    assert [(i.kind, i.name) for i in fn.inputs] == [("node", "3"), ("node", "4"), ("input", "u1")]


def test_include_example():
    net = load("examples/tclab_include.thn")
    board = load("tclab/tclab.thn")
    assert any(f.endswith("tclab_board.thi") for f in net.source_files)
    assert net.node_names == board.node_names
    assert [p.name for p in board.params] == [p.name for p in net.params if p.name in board.param_names]
    for p in board.params:
        if isinstance(p.expr, Num):
            assert value(net, p.name) == p.expr.value
    t1 = net.sensors[0]
    assert t1.lag and value(net, t1.lag) == 20.0 and net.sensors[1].lag is None


def test_subnet_example():
    net = load("examples/two_rooms_subnet.thn")
    assert net.node_names == ["r1.air", "r2.air"]
    assert value(net, net.nodes[0].capacitance) == pytest.approx(2e5)
    assert value(net, net.nodes[1].capacitance) == pytest.approx(3e5)
    walls = {l.a: value(net, l.value) for l in net.links if l.b == "amb"}
    assert walls == {"r1.air": pytest.approx(0.01), "r2.air": pytest.approx(0.008)}
    inner = next(l for l in net.links if l.name == "R_inner")
    assert {inner.a, inner.b} == {"r1.air", "r2.air"} and net.param("R_inner").free
    heaters = {s.node: net.param(s.value).expr.name for s in net.sources}
    assert heaters == {"r1.air": "P1", "r2.air": "P2"}
    assert all(not math.isnan(value(net, n.capacitance)) for n in net.nodes)
