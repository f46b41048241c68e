"""Values written as expressions are checked like written numbers; a boundary's implicit name collides clearly.

A capacity, resistance, conductance or time constant written as an expression of constants is evaluated with
the written values (SI) and must be positive and finite; a division by a constant zero is an error at the
division, also in an expression that reads inputs or temperatures; a node's `C_x` or a boundary's `T_x` that
takes a name the user declared is an error at the element naming both declarations.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tnn_dsl
from tnn_dsl import TnnError
from tnn_dsl.cli import main

HEAD = "network t\nboundary amb = 20 degC\n"

# (text, line, col, words in the message, the hint's words)
CASES = {
    "negative capacity": (HEAD + "param c0 = 5 J/K\nnode a C = c0 - 8 J/K\nG a -- amb = 1 W/K\n", 4, 12,
                          ["the capacity of node `a` must be positive", "`C_a` evaluates to -3 J/K"], "`c0`"),
    "zero resistance": (HEAD + "node a C = 10 J/K\nR a -- amb = 0.3 * 0 K/W\n", 4, 14,
                        ["R a -- amb must be positive", "`R_a_amb` evaluates to 0 K/W"], "no physical meaning"),
    "zero capacity": (HEAD + "node a C = 2 J/K - 2 J/K\nG a -- amb = 1 W/K\n", 3, 12,
                      ["the capacity of node `a` must be positive", "evaluates to 0 J/K"], "no physical meaning"),
    "negative conductance": (HEAD + "param g = 2 W/K\nnode a C = 1 J/K\nG a -- amb = g - 3 W/K\n", 5, 14,
                             ["G a -- amb must be positive", "`G_a_amb` evaluates to -1 W/K"], "`g`"),
    "negative lag": (HEAD + "param tau = 4 s\nnode a C = 1 J/K\nG a -- amb = 1 W/K\nsensor S = a lag 1 s - tau\n",
                     6, 18, ["the lag of sensor `S` must be positive", "`S.lag` evaluates to -3 s"], "`tau`"),
    "below absolute zero": ("network t\nparam d = 400 K\nboundary amb = 20 degC - d\nnode a C = 1 J/K\n"
                            "G a -- amb = 1 W/K\n", 3, 16,
                            ["`T_amb` is at or below absolute zero: it evaluates to -106.85 K"], "kelvin"),
    "emissivity above 1": (HEAD + "node a C = 1 J/K\nG a -- amb = 1 W/K\n"
                           "radiation a -- amb area = 1 m^2 emissivity = 0.6 * 2\n", 5, 46,
                           ["`rad_a_amb.emissivity` must be at most 1, but it evaluates to 1.2"],
                           "check the expression"),
    "division by zero": (HEAD + "param x = 3 J/K\nnode a C = x / 0\nG a -- amb = 1 W/K\n", 4, 12,
                         ["division by zero in `C_a`"], "written as 0"),
    "division by a zero parameter": (HEAD + "param z = 1 - 1\nnode a C = 2 J/K / z\nG a -- amb = 1 W/K\n", 4, 12,
                                     ["division by zero in `C_a`"], "evaluates to 0"),
    "division by zero with an input": (HEAD + "input u : [W/K]\nnode a C = 1 J/K\nG a -- amb = 2 * (u / 0)\n",
                                       5, 19, ["division by zero in `G_a_amb`"], "written as 0"),
    "division by zero with a temperature": (HEAD + "node a C = 1 J/K\nG a -- amb = 1 W/K\n"
                                            "source a = T(a) * 1 W/K / (2 - 2)\n", 5, 12,
                                            ["division by zero in `Q_src_a`"], "evaluates to 0"),
    "zero to a negative power": (HEAD + "param z = 0\nnode a C = 1 J/K * z ^ -1\nG a -- amb = 1 W/K\n", 4, 20,
                                 ["division by zero in `C_a`", "negative power"], None),
    "parallel of a zero": (HEAD + "node a C = 1 J/K\nR a -- amb = parallel(1 K/W, 0 K/W)\n", 4, 14,
                           ["division by zero in `R_a_amb`", "`parallel`"], "no argument may be zero"),
    "log of zero": (HEAD + "param z = 0\nnode a C = 1 J/K * log(z)\nG a -- amb = 1 W/K\n", 4, 20,
                    ["`log` of 0 in `C_a`"], "not positive"),
    "overflow": (HEAD + "node a C = 1e300 J/K * 1e300\nG a -- amb = 1 W/K\n", 3, 12,
                 ["`C_a` is not a finite number", "inf"], "overflows"),
    "boundary temperature named like an input": (
        "network t\ninput T_ext : temperature\nboundary ext = T_ext\nnode a C = 1 J/K\nG a -- ext = 1 W/K\n", 3, 1,
        ["boundary `ext` names its temperature parameter `T_ext`, but `T_ext` is already an input"],
        "rename the input"),
    "boundary temperature named like a later input": (
        "network t\nboundary ext = 20 degC\ninput T_ext : temperature\nnode a C = 1 J/K\nG a -- ext = 1 W/K\n",
        2, 1, ["boundary `ext` names its temperature parameter `T_ext`"], "rename the input"),
    "boundary temperature named like a later parameter": (
        "network t\nboundary ext = T_ext\nparam T_ext = 20 degC\nnode a C = 1 J/K\nG a -- ext = 1 W/K\n", 2, 1,
        ["boundary `ext` names its temperature parameter `T_ext`, but `T_ext` is already a parameter"],
        "rename the parameter"),
    "node capacity named like a parameter": (
        HEAD + "param C_a = 5 J/K\nnode a C = C_a\nG a -- amb = 1 W/K\n", 4, 1,
        ["node `a` names its capacity parameter `C_a`, but `C_a` is already a parameter"], "`C_NAME`"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_loads_reports_the_value_at_its_position(name):
    text, line, col, words, hint = CASES[name]
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(text, "x.thn")
    (d,) = info.value.diagnostics  # one problem, one message: no cascade ("depends on itself", ...)
    assert (d.span.file, d.span.line, d.span.col) == ("x.thn", line, col), d.format()
    for w in words:
        assert w in d.message
    if hint is not None:
        assert hint in d.hint


def test_collision_names_both_declarations():
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(CASES["boundary temperature named like an input"][0], "x.thn")
    (d,) = info.value.diagnostics
    assert [(what, s.line) for what, s in d.related] == [("the input `T_ext` is declared here", 2)]


@pytest.mark.parametrize("name", ["negative capacity", "zero resistance", "zero capacity", "division by zero",
                                  "division by zero with an input", "boundary temperature named like an input"])
def test_tnnc_check_exits_1_with_the_message(name, tmp_path, capsys):
    text, line, col, words, _ = CASES[name]
    path = tmp_path / "x.thn"
    path.write_text(text)
    assert main(["check", str(path)]) == 1
    out = capsys.readouterr()
    both = out.out + out.err
    assert f"x.thn:{line}:{col}: error: {words[0]}" in both
    assert "^" in both and "hint:" in both
    assert "Traceback" not in both


@pytest.mark.parametrize("expr", ["c0 + 8 J/K", "c0 * 2 / 4", "max(c0, 1 J/K) - 1 J/K / 2", "series(c0, c0)",
                                  "c0 * (2 ^ -1)", "c0 / sqrt(4)"])
def test_positive_constant_expressions_load(expr):
    net = tnn_dsl.loads(HEAD + f"param c0 = 5 J/K\nnode a C = {expr}\nG a -- amb = 1 W/K\n", "x.thn")
    assert net.param("C_a").expr.op != "num"


def test_expressions_of_inputs_and_temperatures_are_not_judged_by_value():
    # an input may be zero or negative at some instant: only a constant zero divisor is known to be wrong
    net = tnn_dsl.loads(HEAD + "input u : [1]\nnode a C = 1 J/K * u\nG a -- amb = 1 W/K / u\n"
                               "source a = (T(a) - T(amb)) * 1 W/K / u\n", "x.thn")
    assert {p.name for p in net.params} >= {"C_a", "G_a_amb", "Q_src_a"}


def test_input_named_like_a_boundary_temperature_can_be_renamed():
    net = tnn_dsl.loads("network t\ninput T_ext_in : temperature\nboundary ext = T_ext_in\nnode a C = 1 J/K\n"
                        "G a -- ext = 1 W/K\n", "x.thn")
    assert net.boundaries[0].temperature == "T_ext"


# -- property: a capacity written as any expression of positive literals -----------------------------------


def _lit(v: float) -> tuple[str, float]:
    return repr(v), v


def _combine(op, a, b):
    """The text and the float value (``None``: a division by zero or an overflow on the way) of `a op b`."""
    (ta, va), (tb, vb) = a, b
    if va is None or vb is None or (op == "/" and vb == 0):
        v = None
    else:
        v = va + vb if op == "+" else va - vb if op == "-" else va * vb if op == "*" else va / vb
        v = v if math.isfinite(v) else None
    return f"({ta} {op} {tb})", v


_POSITIVE = st.floats(min_value=1e-3, max_value=1e300, allow_nan=False, allow_infinity=False)
_NUMBER = st.recursive(_POSITIVE.map(_lit),
                       lambda kids: st.builds(_combine, st.sampled_from("+-*/"), kids, kids), max_leaves=6)


def _capacity(leaf):
    def with_unit(n):
        return f"(1 J/K * {n[0]})", (None if n[1] is None else 1.0 * n[1])

    def scale(c, op, n):
        return _combine(op, c, n)

    return st.recursive(
        leaf.map(with_unit),
        lambda kids: st.one_of(st.builds(_combine, st.sampled_from("+-"), kids, kids),
                               st.builds(scale, kids, st.sampled_from("*/"), _NUMBER)),
        max_leaves=6)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_capacity(_NUMBER))
def test_any_capacity_expression_loads_positive_or_names_the_parameter(cap):
    text, value = cap
    src = HEAD + f"node a C = {text}\nG a -- amb = 1 W/K\n"
    try:
        tnn_dsl.loads(src, "x.thn")
    except TnnError as err:
        # value None: a division by zero or an overflow on the way; otherwise zero or negative
        assert value is None or value <= 0, err
        assert err.diagnostics and all("`C_a`" in d.message and d.span.line == 3 for d in err.diagnostics), err
    else:
        assert value is not None and value > 0, (text, value)
