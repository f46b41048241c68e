"""Parser: expressions, spans, clauses in any order, includes, subnets, several syntax errors at once."""

from __future__ import annotations

import pytest

import tnn_dsl
from tnn_dsl import TnnError
from tnn_dsl.ir.network import Binary, Call, Num, Ref, Temp, Unary

HEAD = "network t\nboundary amb = 20 degC\nnode a C = 10 J/K\nG a -- amb = 1 W/K\n"


def load(text, name="t.thn"):
    return tnn_dsl.loads(HEAD + text, name)


def test_expression_precedence_and_spans():
    net = load("param x = 1 W + 2 W * 3 ^ 2 / 4 - -1 W\n")
    e = net.param("x").expr
    # ((1 + ((2 * 3^2) / 4)) - (-1))
    assert isinstance(e, Binary) and e.op == "-"
    assert e.left.op == "+" and e.left.right.op == "/" and e.left.right.left.right.op == "^"
    assert isinstance(e.right, Num) and e.right.value == -1.0
    assert e.span.line == 5 and e.span.col == 11
    assert e.left.left.span.col == 11 and e.left.left.span.end_col == 14


def test_negative_temperature_literal_is_minus_degrees():
    net = load("boundary cold = -5 degC\nparam d = -(5 degC)\n")
    assert net.param("T_cold").value == pytest.approx(268.15)
    assert isinstance(net.param("d").expr, Unary) and net.param("d").expr.arg.value == pytest.approx(278.15)


def test_bare_number_in_temperature_slot_uses_file_unit():
    net = tnn_dsl.loads("network t\nunits temperature = degF\nboundary amb = 212\nnode a C = 1 J/K\n"
                        "G a -- amb = 1 W/K\n", "t.thn")
    assert net.param("T_amb").value == pytest.approx(373.15)
    assert net.temperature_unit == "degF"


def test_functions_and_temperatures():
    net = load("node 3 C = 1 J/K\nG 3 -- amb = 1 W/K\n"
               "param x = max(T(a), T3) - min(T(a), amb) + abs(T(a) - 300 K) + sqrt(4 K^2)\n")
    e = net.param("x").expr
    calls = []

    def walk(n):
        if isinstance(n, Call):
            calls.append(n.fn)
            for a in n.args:
                walk(a)
        elif isinstance(n, Binary):
            walk(n.left), walk(n.right)
    walk(e)
    assert calls == ["max", "min", "abs", "sqrt"]
    mx = e.left.left.left
    assert [a.node for a in mx.args] == ["a", "3"] and all(isinstance(a, Temp) for a in mx.args)
    assert isinstance(e.left.left.right.args[1], Temp)  # bare boundary name -> its temperature


def test_clauses_in_any_order_and_labels():
    net = load('G a -- amb = 2 W/K as Gx free "label x"\nsensor S "probe" = a column "c" offset 0.5 K lag 3 s\n')
    link = next(l for l in net.links if l.name == "Gx")
    assert link.label == "label x" and net.param("Gx").free
    s = net.sensors[0]
    assert (s.label, s.column, s.lag, s.offset) == ("probe", "c", "S.lag", "S.offset")
    assert net.param("S.offset").value == 0.5


def test_repeated_links_get_numbered_names():
    net = load("G a -- amb = 2 W/K\nG a -- amb = 3 W/K\nsource a = 1 W\nsource a = 2 W\n")
    assert [l.name for l in net.links] == ["G_a_amb", "G_a_amb_2", "G_a_amb_3"]
    assert [s.name for s in net.sources] == ["Q_src_a", "Q_src_a_2"]


def test_multiline_inside_brackets_and_comments():
    net = load("param x = max(1 W,   # first\n   2 W,\n   3 W)  # last\n")
    assert len(net.param("x").expr.args) == 3


def test_learn_options_outside_parentheses_and_defaults():
    net = load("input u : [1]\nlearn C_a as mlp(a, u)\nlearn G_a_amb as poly(u)\n")
    mlp, poly = net.learned
    assert mlp.hidden == [8, 8] and mlp.activation == "tanh" and poly.degree == 2
    assert [f.name for f in net.learned] == ["fn_C_a", "fn_G_a_amb"]


def test_include_relative_and_cycle(tmp_path):
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "box.thn").write_text("node b C = 2 J/K\nG b -- amb = 1 W/K\n")
    (tmp_path / "main.thn").write_text(HEAD + 'include "parts/box.thn"\n')
    net = tnn_dsl.load(tmp_path / "main.thn")
    assert [n.name for n in net.nodes] == ["a", "b"]
    assert any(f.endswith("box.thn") for f in net.source_files)
    (tmp_path / "x.thn").write_text('include "y.thn"\n')
    (tmp_path / "y.thn").write_text('include "x.thn"\n')
    (tmp_path / "cyc.thn").write_text(HEAD + 'include "x.thn"\n')
    with pytest.raises(TnnError) as info:
        tnn_dsl.load(tmp_path / "cyc.thn")
    assert "include cycle: cyc.thn -> x.thn -> y.thn -> x.thn" in str(info.value)


def test_include_file_may_not_name_network(tmp_path):
    (tmp_path / "inc.thn").write_text("network other\n")
    (tmp_path / "main.thn").write_text(HEAD + 'include "inc.thn"\n')
    with pytest.raises(TnnError, match="`network` in an included file"):
        tnn_dsl.load(tmp_path / "main.thn")


SUBNET = '''
subnet heater(C0, G0) "a heater block on a plate"
    node core C = C0 free
    node case C = 2 J/K
    G core -- case = G0
    G case -- amb = 0.1 W/K        # amb is not declared inside: the enclosing network's
    sensor T = core column "T"
end
use heater(C0 = 4 J/K, G0 = 0.05 W/K) as h1
use heater(C0 = 6 J/K, G0 = 0.04 W/K) as h2
G h1.case -- h2.case = 0.01 W/K
learn h1.G_core_case, h2.C_core as const
'''


def test_subnet_instances_with_dotted_names():
    net = load(SUBNET)
    assert [n.name for n in net.nodes] == ["a", "h1.core", "h1.case", "h2.core", "h2.case"]
    assert net.param("h1.C_core").value == 4 and net.param("h1.C_core").free
    assert net.param("h2.C_core").value == 6
    assert net.param("h2.G_core_case").value == 0.04
    assert [(l.a, l.b) for l in net.links if l.name == "h1.G_case_amb"] == [("h1.case", "amb")]
    assert [s.name for s in net.sensors] == ["h1.T", "h2.T"]
    assert [t.name for t in net.learned[0].targets] == ["h1.G_core_case", "h2.C_core"]


def test_nested_subnets_and_recursion():
    text = ("subnet leaf(C0)\nnode n C = C0\nG n -- amb = 1 W/K\nend\n"
            "subnet pair\nuse leaf(C0 = 1 J/K) as l\nuse leaf(C0 = 2 J/K) as r\nG l.n -- r.n = 1 W/K\nend\n"
            "use pair as p\n")
    net = load(text)
    assert [n.name for n in net.nodes][1:] == ["p.l.n", "p.r.n"]
    assert [(l.a, l.b) for l in net.links][-1] == ("p.l.n", "p.r.n")
    with pytest.raises(TnnError, match="uses itself"):
        load("subnet s\nuse s as x\nend\nuse s as y\n")


def test_several_syntax_errors_reported_together():
    text = HEAD + "param x = 3 W/K 4\nnode b C =\nR a b = 1 K/W\nparam ok = 1 W\n"
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(text, "t.thn")
    lines = [d.span.line for d in info.value.diagnostics]
    assert lines == [5, 6, 7]
    assert str(info.value).endswith("3 errors")


def test_error_format_has_caret_and_hint():
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(HEAD + "R a -- amb = 0.08 W/K\n", "t.thn")
    out = str(info.value).splitlines()
    assert out[0] == "t.thn:5:14: error: R a -- amb is a resistance (K/W) but was given in W/K"
    assert out[1] == " 5 | R a -- amb = 0.08 W/K"
    assert out[2] == "   |              ^^^^^^^^"
    assert out[3].startswith("hint: a resistance is in K/W; use `G a -- b = ...`")


def test_non_utf8_reports_first_bad_byte(tmp_path):
    p = tmp_path / "bad.thn"
    p.write_bytes(b"network x\nnode ab\xe9 C = 1 J/K\n")
    with pytest.raises(TnnError) as info:
        tnn_dsl.load(p)
    assert str(info.value).startswith(f"{p}:2:8: error: the file is not UTF-8 text: byte 0xe9")


def test_missing_file():
    with pytest.raises(TnnError, match="no such file"):
        tnn_dsl.load("/nonexistent/x.thn")


def test_ir_json_round_trip():
    net = load(SUBNET + "param k = 0.02 1/K\nparam r = 0.2 K/W * (1 - k * (T(a) - 25 degC))\n")
    again = tnn_dsl.Network.from_json(net.to_json())
    assert again.to_json() == net.to_json()
    assert isinstance(again.param("r").expr.right.right.right.left, Temp)
    assert isinstance(again.param("r").expr.right.right.left, Ref)


def test_grammar_is_found_from_package_resources(monkeypatch):
    from tnn_dsl.lang import grammar as _parser

    text = _parser._grammar_text()
    assert "start:" in text and "propagate" not in text.split("start:")[1][:0]


def test_statement_walk_matches_lark_transformer_on_every_shipped_network():
    """The parser's own bottom-up walk (callbacks looked up once per rule) gives exactly the statements lark's
    ``Transformer.transform`` gives, on every network in ``networks/`` and the examples."""
    from pathlib import Path

    from lark import Transformer

    from tnn_dsl.lang.statements import _parse_text, _ToStatements

    root = Path(__file__).resolve().parents[1]
    files = sorted(root.glob("networks/**/*.thn")) + sorted(root.glob("examples/**/*.thn"))
    assert len(files) >= 10
    for f in files:
        tree, diags = _parse_text(f.read_text(encoding="utf-8"), str(f))
        assert not diags, f
        ours = _ToStatements(str(f), []).transform(tree)
        lark_walk = Transformer.transform(_ToStatements(str(f), []), tree)
        assert ours == lark_walk, f


def test_collector_paused_restores_the_previous_state_even_on_errors():
    import gc

    from tnn_dsl.core.collector import collector_paused

    assert gc.isenabled()
    with collector_paused():
        assert not gc.isenabled()
        with collector_paused():
            assert not gc.isenabled()
        assert not gc.isenabled()  # only the outermost exit restores
    assert gc.isenabled()
    with pytest.raises(tnn_dsl.TnnError):
        tnn_dsl.loads("node a C = \n", "bad.thn")
    assert gc.isenabled()
    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()  # it was off before: it stays off
    finally:
        gc.enable()
