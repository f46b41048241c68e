"""Every code example of ../shared/spec/thn-by-example.md parses and means what its comments say.
The examples are copied here verbatim (the spec lives outside the repository)."""

from __future__ import annotations

import pytest

import tnn_dsl
from tnn_dsl import TnnError

TCLAB = '''
network tclab "Temperature Control Lab: two transistor heaters on one board"

units temperature = degC            # temperatures in this file and in data columns; the math runs in kelvin

input Q1 : [%]  column "Q1_pct"     # heater commands, read from the data file's columns
input Q2 : [%]  column "Q2_pct"

param Ta  = 23 degC    free in [15 degC, 30 degC]   # ambient was not logged: estimate it
param a1  = 0.01 W/%   free in [0, 0.05 W/%]        # heater gains
param a2  = 0.0075 W/% free in [0, 0.05 W/%]

boundary amb = Ta

node h1 "heater 1"  C = 4 J/K  free
node h2 "heater 2"  C = 4 J/K  free

G h1 -- amb = 0.05 W/K  free  as U1
G h2 -- amb = 0.05 W/K  free  as U2
G h1 -- h2  = 0.02 W/K  free  as U12

source h1 = a1 * Q1                 # heat load into a node, any expression of params and inputs
source h2 = a2 * Q2

sensor T1 = h1  column "T1_degC"    # what the data measures, and where
sensor T2 = h2  column "T2_degC"
'''

TCLAB_MISSES = '''
sensor T1 = h1  lag 20 s free  column "T1_degC"    # first-order sensor dynamics
radiation h1 -- amb  area = 1e-3 m^2  emissivity = 0.9 free
'''

M2 = '''
network peltier_heatpipe "Peltier cooler with heat pipe and two fluid heat exchangers"
units temperature = degC

input I   : [A]       "Peltier current"
input u1  : [1]       "heat-pipe operating input"
input Ta  : temperature
input Tf1 : temperature  "fluid 1 inlet"
input Tf2 : temperature  "fluid 2 inlet"

node ph   "Peltier hot side"   C = 40 J/K
node pc   "Peltier cold side"  C = 40 J/K
node hs   "heat sink"          C = 600 J/K
node hx1  "heat exchanger 1"   C = 300 J/K
node hp   "heat pipe"          C = 60 J/K
node hx2  "heat exchanger 2"   C = 300 J/K
node base "mounting plate"     C = 800 J/K

boundary amb = Ta

R ph  -- hs   = 0.08 K/W
R pc  -- hx1  = 0.05 K/W
R hx1 -- hp   = 0.2 K/W   as R_hp1
R hp  -- hx2  = 0.2 K/W   as R_hp2
R hp  -- amb  = 10 K/W    as R_hpa
R hs  -- amb  = 0.3 K/W
R base -- hs  = 2 K/W
R base -- hx1 = 2 K/W
R base -- amb = 3 K/W

peltier pe  hot = ph  cold = pc  current = I  seebeck = 0.05 V/K free  resistance = 2 ohm free  R_internal = 1.5 K/W
fluid f1  through hx1  inlet = Tf1  mdot = 0.002 kg/s  cp = 4186 J/(kg*K)  UA = 5 W/K
fluid f2  through hx2  inlet = Tf2  mdot = 0.002 kg/s  cp = 4186 J/(kg*K)  UA = 5 W/K

sensor T_out = hx2

learn R_hp1, R_hp2, R_hpa as linear(hx1, hp, hx2, u1)
'''
M2_BODY = M2.rsplit("learn", 1)[0]

VARIANTS = {
    "M1": "learn R_hp1, R_hp2, R_hpa as const",
    "M3": "learn R_hp1, R_hp2, R_hpa as mlp(hx1, hp, hx2, u1; hidden = [8, 8], activation = sigmoid)",
    "M4": "learn pe.Q_hot, pe.Q_cold as mlp(ph, pc, I; hidden = [8, 8])",
}

DESIGN_CARD = '''
node 3 C = 300 J/K
node 4 C = 60 J/K
R 3 -- 4 = 0.2 K/W  as R_hp
learn R_hp as mlp(T3, T4, u1)        # T3 is the temperature of node 3
'''
DESIGN_CARD_CONTEXT = "network card\ninput u1 : [1]\nboundary amb = 20 degC\nG 4 -- amb = 1 W/K\n"

R_ = {"kg": -1.0, "m": -2.0, "s": 3.0, "K": 1.0}
G_ = {"kg": 1.0, "m": 2.0, "s": -3.0, "K": -1.0}


def test_tclab_means_what_it_says():
    net = tnn_dsl.loads(TCLAB, "tclab.thn")
    assert net.name == "tclab" and net.label.startswith("Temperature Control Lab")
    assert net.temperature_unit == "degC"
    assert [(i.name, i.column, i.unit, i.is_temperature) for i in net.inputs] == [
        ("Q1", "Q1_pct", "%", False), ("Q2", "Q2_pct", "%", False)]
    ta = net.param("Ta")
    assert ta.value == pytest.approx(296.15) and ta.free
    assert (ta.lower, ta.upper) == (pytest.approx(288.15), pytest.approx(303.15))
    a1 = net.param("a1")
    assert a1.value == pytest.approx(1.0)  # 0.01 W per percent = 1 W per unit fraction
    assert (a1.lower, a1.upper) == (0.0, pytest.approx(5.0))
    assert net.param("a2").value == pytest.approx(0.75)
    assert net.boundaries[0].name == "amb" and net.param("T_amb").expr.name == "Ta"
    assert net.param("T_amb").expr.kind == "param"
    assert [(n.name, n.label, n.capacitance) for n in net.nodes] == [
        ("h1", "heater 1", "C_h1"), ("h2", "heater 2", "C_h2")]
    c = net.param("C_h1")
    assert c.value == 4.0 and c.free and c.role == "capacitance"
    assert [(l.name, l.a, l.b, l.form) for l in net.links] == [
        ("U1", "h1", "amb", "G"), ("U2", "h2", "amb", "G"), ("U12", "h1", "h2", "G")]
    u1 = net.param("U1")
    assert u1.role == "conductance" and u1.free and u1.value == 0.05 and u1.dim == G_
    src = net.param("Q_src_h1")
    assert [s.node for s in net.sources] == ["h1", "h2"] and src.role == "heat_flow"
    assert src.expr.op == "*" and src.expr.left.kind == "param" and src.expr.right.kind == "input"
    assert src.dim == {"kg": 1.0, "m": 2.0, "s": -3.0}
    assert [(s.name, s.node, s.column, s.lag) for s in net.sensors] == [
        ("T1", "h1", "T1_degC", None), ("T2", "h2", "T2_degC", None)]
    assert {p.name for p in net.free_params} == {"Ta", "a1", "a2", "C_h1", "C_h2", "U1", "U2", "U12"}


def test_tclab_with_what_the_two_node_model_misses():
    text = TCLAB.replace('sensor T1 = h1  column "T1_degC"    # what the data measures, and where\n', "")
    net = tnn_dsl.loads(text + TCLAB_MISSES, "tclab_lag.thn")
    t1 = next(s for s in net.sensors if s.name == "T1")
    assert t1.lag == "T1.lag" and t1.column == "T1_degC"
    lag = net.param("T1.lag")
    assert lag.value == 20.0 and lag.free and lag.role == "time_constant"
    rad = net.radiations[0]
    assert (rad.name, rad.a, rad.b) == ("rad_h1_amb", "h1", "amb")
    assert net.param(rad.area).value == pytest.approx(1e-3)
    em = net.param(rad.emissivity)
    assert em.value == 0.9 and em.free and em.name == "rad_h1_amb.emissivity"
    assert net.param(rad.view_factor).value == 1.0


def test_case_study_m2():
    net = tnn_dsl.loads(M2, "m2.thn")
    assert [n.name for n in net.nodes] == ["ph", "pc", "hs", "hx1", "hp", "hx2", "base"]
    assert [net.param(n.capacitance).value for n in net.nodes] == [40, 40, 600, 300, 60, 300, 800]
    ta = next(i for i in net.inputs if i.name == "Ta")
    assert ta.is_temperature and ta.dim == {"K": 1.0} and ta.column == "Ta"
    assert next(i for i in net.inputs if i.name == "I").dim == {"A": 1.0}
    assert next(i for i in net.inputs if i.name == "u1").label == "heat-pipe operating input"
    names = [l.name for l in net.links]
    assert names == ["R_ph_hs", "R_pc_hx1", "R_hp1", "R_hp2", "R_hpa", "R_hs_amb",
                     "R_base_hs", "R_base_hx1", "R_base_amb"]
    assert net.param("R_hpa").value == 10 and net.param("R_hpa").role == "resistance"
    assert net.param("R_ph_hs").dim == R_
    pe = net.peltiers[0]
    assert (pe.hot, pe.cold, pe.current, pe.seebeck, pe.resistance, pe.r_internal) == (
        "ph", "pc", "pe.current", "pe.seebeck", "pe.resistance", "pe.R_internal")
    assert net.param("pe.current").expr.name == "I" and net.param("pe.current").expr.kind == "input"
    assert net.param("pe.seebeck").free and net.param("pe.seebeck").value == 0.05
    assert net.param("pe.resistance").free and net.param("pe.resistance").value == 2
    assert net.param("pe.R_internal").value == 1.5 and net.param("pe.R_internal").role == "resistance"
    f1 = net.fluids[0]
    assert (f1.name, f1.node, f1.inlet, f1.mdot, f1.cp, f1.ua) == ("f1", "hx1", "f1.inlet", "f1.mdot", "f1.cp", "f1.UA")
    assert net.param("f1.cp").value == 4186 and net.param("f1.UA").value == 5
    assert net.param("f1.inlet").expr.name == "Tf1"
    assert [(s.name, s.node, s.column) for s in net.sensors] == [("T_out", "hx2", "T_out")]
    (fn,) = net.learned
    assert fn.kind == "linear"
    assert [(t.kind, t.name) for t in fn.targets] == [("param", "R_hp1"), ("param", "R_hp2"), ("param", "R_hpa")]
    assert [(i.kind, i.name) for i in fn.inputs] == [("node", "hx1"), ("node", "hp"), ("node", "hx2"), ("input", "u1")]
    assert fn.name not in {"f1", "f2"}  # learned-function names never collide with element names
    assert set(net.learned_targets()) == {"R_hp1", "R_hp2", "R_hpa"}


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_case_study_variants(variant):
    net = tnn_dsl.loads(M2_BODY + VARIANTS[variant] + "\n", f"{variant}.thn")
    (fn,) = net.learned
    if variant == "M1":
        assert fn.kind == "const" and fn.inputs == [] and len(fn.targets) == 3
    elif variant == "M3":
        assert fn.kind == "mlp" and fn.hidden == [8, 8] and fn.activation == "sigmoid"
        assert [i.name for i in fn.inputs] == ["hx1", "hp", "hx2", "u1"]
    else:
        assert fn.kind == "mlp" and fn.hidden == [8, 8]
        assert [(t.kind, t.name) for t in fn.targets] == [("flow", "pe.Q_hot"), ("flow", "pe.Q_cold")]
        assert [(i.kind, i.name) for i in fn.inputs] == [("node", "ph"), ("node", "pc"), ("input", "I")]


def test_case_study_m5_frozen_peltier_net_and_heat_pipe_net(tmp_path):
    text = M2_BODY + (
        'learn pe.Q_hot, pe.Q_cold as mlp(ph, pc, I; hidden = [8, 8], frozen, init_from = "models/m4")\n'
        "learn R_hp1, R_hp2, R_hpa as mlp(hx1, hp, hx2, u1; hidden = [8, 8], activation = sigmoid)\n")
    (tmp_path / "m5.thn").write_text(text)
    net = tnn_dsl.load(tmp_path / "m5.thn")
    pel, hp = net.learned
    assert pel.frozen and pel.init_from == str(tmp_path / "models" / "m4")
    assert not hp.frozen and hp.activation == "sigmoid"
    assert pel.name != hp.name


def test_design_card_numbered_nodes():
    net = tnn_dsl.loads(DESIGN_CARD_CONTEXT + DESIGN_CARD, "card.thn")
    assert [n.name for n in net.nodes] == ["3", "4"]
    assert net.param("C_3").value == 300
    assert [(l.name, l.a, l.b) for l in net.links if l.name == "R_hp"] == [("R_hp", "3", "4")]
    (fn,) = net.learned
    assert [(i.kind, i.name) for i in fn.inputs] == [("node", "3"), ("node", "4"), ("input", "u1")]


def test_section3_forms():
    text = M2_BODY + '''
param R_hp_true = 0.2 K/W * (1 + 1.5*(u1 - 0.5) - 0.02 1/K * (mean(T(hx1), T(hp)) - 25 degC))
node cu C = 10 J/K
G cu -- amb = table(mean(cu, amb); 0 degC: 2.0 W/K, 50 degC: 2.4 W/K)
R cu -- base = series(1 K/W, parallel(2 K/W, 2 K/W))
learn Q[hx2] as mlp(hx2, u1)
learn pe.seebeck as poly(ph, pc; degree = 2)
learn C_hp as table(hp; knots = [0 degC, 25 degC, 50 degC])
'''
    net = tnn_dsl.loads(text, "s3.thn")
    p = net.param("R_hp_true")
    assert p.dim == R_ and not p.is_constant
    g = net.param("G_cu_amb").expr
    assert g.op == "table" and g.xs == [pytest.approx(273.15), pytest.approx(323.15)] and g.ys == [2.0, 2.4]
    assert [a.op for a in g.x.args] == ["temp", "temp"]
    assert net.param("R_cu_base").expr.fn == "series"
    kinds = {fn.kind: fn for fn in net.learned}
    assert [(t.kind, t.name) for t in kinds["mlp"].targets] == [("heat_load", "hx2")]
    assert kinds["poly"].degree == 2 and kinds["poly"].targets[0].name == "pe.seebeck"
    assert kinds["table"].knots == [pytest.approx(273.15), pytest.approx(298.15), pytest.approx(323.15)]


def test_resistance_given_in_w_per_k_names_both_units():
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(M2.replace("R ph  -- hs   = 0.08 K/W", "R ph  -- hs   = 0.08 W/K"), "m2.thn")
    assert "R ph -- hs is a resistance (K/W) but was given in W/K" in str(info.value)
