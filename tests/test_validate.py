"""The validation pass: all problems at once, resolution of names and dimensions."""

from __future__ import annotations

import pytest

import tnn_dsl
from tnn_dsl import TnnError

HEAD = "network t\nboundary amb = 20 degC\nnode a C = 10 J/K\nG a -- amb = 1 W/K\n"


def errors(text, name="t.thn"):
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(text, name)
    return info.value.diagnostics


def test_all_problems_reported_together_sorted():
    ds = errors(HEAD + "node b C = -1 J/K\nG b -- amb = 1 K/W\nsensor S = nowhere\nlearn R_x as const\n"
                       "source a = q * 2\n")
    msgs = [d.message for d in ds]
    assert len(ds) == 5
    assert [d.span.line for d in ds] == sorted(d.span.line for d in ds)
    assert any("must be positive" in m for m in msgs)
    assert any("conductance (W/K) but was given in K/W" in m for m in msgs)
    assert any("there is no node `nowhere`" in m for m in msgs)
    assert any("cannot learn `R_x`" in m for m in msgs)
    assert any("undefined name `q`" in m for m in msgs)


def test_duplicate_has_first_defined_note():
    (d,) = errors(HEAD + "param p = 1 W\nparam p = 2 W\n")
    assert d.message == "the name `p` is already a parameter"
    assert d.related[0][0] == "first defined here" and d.related[0][1].line == 5
    assert "note: first defined here" in d.format()


def test_duplicate_node_reported_once():
    ds = errors(HEAD + "node a C = 3 J/K\n")
    assert [d.message for d in ds] == ["node `a` is defined twice"]


def test_singular_component():
    (d,) = errors(HEAD + "node b C = 1 J/K\nnode c C = 1 J/K\nG b -- c = 1 W/K\n")
    assert d.message == "nodes `b`, `c` have no conduction path to a boundary or a fluid inlet"
    assert "steady state is undefined" in d.hint


def test_fluid_inlet_anchors_a_component():
    net = tnn_dsl.loads(HEAD + "node b C = 1 J/K\nfluid f through b inlet = 20 degC mdot = 1 kg/s "
                               "cp = 4186 J/(kg*K) UA = 5 W/K\n", "t.thn")
    assert net.fluids[0].node == "b"


def test_peltier_without_internal_resistance_does_not_connect():
    ds = errors(HEAD + "input I : [A]\nnode c C = 1 J/K\n"
                       "peltier pe hot = a cold = c current = I seebeck = 0.05 V/K resistance = 2 ohm\n")
    assert "no conduction path" in ds[0].message


@pytest.mark.parametrize("text, message", [
    ("param p = 1 W + 1 K\n", "cannot add a heat flow (W) and a temperature (K)"),
    ("param p = exp(1 K)\n", "`exp` needs a dimensionless argument, got a temperature (K)"),
    ("param p = max(1 K, 1 W)\n", "the arguments of `max` differ: a temperature (K) and a heat flow (W)"),
    ("param p = 2 ^ (1 K)\n", "an exponent must be dimensionless, got a temperature (K)"),
    ("input u : [1]\nparam p = (1 K) ^ u\n", "a temperature (K) raised to a variable power"),
    ("G a -- amb = table(T(a); 0 W: 1 W/K, 1 W: 2 W/K)\n",
     "the table's variable is a temperature (K) but its points are in `W`"),
    ("boundary b = 3 J/K\n", "boundary `b` needs a temperature (K) but was given in J/K"),
    ("input I : [A]\nnode c C = 1 J/K\nG c -- amb = 1 W/K\n"
     "peltier pe hot = a cold = c current = I seebeck = 0.05 V resistance = 2 ohm\n",
     "`pe.seebeck` is a Seebeck coefficient (V/K) but was given in V"),
    ("sensor S = a lag 3 K\n", "the lag of sensor `S` is a time (s) but was given in K"),
    ("param p = 1 K free in [2 K, 3 K]\n", "the bounds of `p` exclude its value 1 (SI; written in K)"),
    ("param p = 1 K free in [3 K, 2 K]\n", "the bounds of `p` are empty: the lower bound is not below the upper one"),
    ("param p = T(zz)\n", "`T(zz)`: there is no node `zz`"),
    ("input u : [1]\nlearn C_a as linear(a, u, nothere)\n",
     "learned-function argument `nothere` is neither a node, an input nor a parameter"),
    ("input u : [1]\nlearn u as const\n", "cannot learn `u`: it is an input (read from data)"),
    ("learn Q[amb] as const\n", "cannot learn `Q[amb]`: there is no node `amb`"),
    ("learn C_a as const(; replace)\n", "`replace` applies to flow targets (`pe.Q_hot`, `f1.Q`) only"),
    ("boundary b2 = 0 K\n", "`T_b2` is at or below absolute zero (0 K)"),
    ("G amb -- amb2 = 1 W/K\nboundary amb2 = 1 degC\n", "link `G_amb_amb2` connects two boundaries"),
])
def test_single_problem_messages(text, message):
    ds = errors(HEAD + text)
    assert message in [d.message for d in ds], [d.message for d in ds]


def test_resolution_of_refs_and_learn_inputs():
    net = tnn_dsl.loads(HEAD + "input u : [1]\nparam k = 2\nnode 7 C = 1 J/K\nG 7 -- a = 1 W/K\n"
                               "param p = k * u * (T7 - a)\nlearn C_a as linear(T7, a, u, k)\n", "t.thn")
    e = net.param("p").expr
    assert e.left.left.kind == "param" and e.left.right.kind == "input"
    assert e.right.left.op == "temp" and e.right.left.node == "7" and e.right.right.node == "a"
    assert net.param("p").dim == {"K": 1.0}
    assert [(i.kind, i.name) for i in net.learned[0].inputs] == [
        ("node", "7"), ("node", "a"), ("input", "u"), ("param", "k")]


def test_hidden_heat_pipe_in_the_language():
    net = tnn_dsl.loads(HEAD + "input u1 : [1]\nnode hp C = 60 J/K\n"
                        "param R_hp1 = 0.2 K/W * (1 + 1.5*(u1 - 0.5) - 0.02 1/K * (mean(T(a), T(hp)) - 25 degC))\n"
                        "R a -- hp = R_hp1\n", "t.thn")
    p = net.param("R_hp1")
    assert p.dim == {"kg": -1.0, "m": -2.0, "s": 3.0, "K": 1.0}
    assert net.param("R_a_hp").expr.kind == "param"
