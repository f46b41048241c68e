"""The simple-line reader (`tnn_dsl.lang.simple_lines`) against the parser: on generated node and link lines —
plain, with odd spacing, keywords as names, malformed numbers and units, labels, clauses, comments, inside
subnets and bracket continuations — reading a file with the simple lines taken out gives the same statements
and the same errors as the parser alone."""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import tnn_dsl
from tnn_dsl.core import TnnError
from tnn_dsl.lang.simple_lines import split_simple_lines
from tnn_dsl.lang.sources import _statements
from tnn_dsl.studies.large_networks import plate_thn

NAMES = ["a", "c0_0", "x.y", "T3", "_b", "3", "007", "3.5", "1e3", ".5", "node", "C", "R", "G", "free", "end",
         "subnet", "as", "cp", "nodeA", "Cx", "a.", "a-b"]
NUMBERS = ["1", "1.67", ".5", "1e3", "1E-3", "2e", "1.", "0", "1e999", "-2", "+2", "1..2", "x"]
UNITS = ["", "W/K", "J/K", "K/W", "W/(m*K)", "kJ/K", "mW/K", "foo", "W/K*2", "1/K", "%", "degC", "W/K/", "W /K",
         "J/kg", "(W/K)^2", "W^2"]
SEPS = [" ", "", "  ", "\t"]
TAILS = ["", "  # a comment", "#x", ' "a label"', " free", " free per experiment", " free in [0, 1 W/K]",
         " as G_x", " + 1 W/K", " (", ")"]


def _read(text: str, simple: bool):
    try:
        return "ok", _statements(text, "t.thn", {}, simple_lines=simple)
    except TnnError as err:
        return "error", [(d.message, d.span, d.hint) for d in err.diagnostics]


line_parts = st.fixed_dictionaries({
    "form": st.sampled_from(["node", "link"]),
    "kind": st.sampled_from(["G", "R"]),
    "lead": st.sampled_from(["", " ", "\t"]),
    "a": st.sampled_from(NAMES), "b": st.sampled_from(NAMES),
    "num": st.sampled_from(NUMBERS), "unit": st.sampled_from(UNITS),
    "s1": st.sampled_from(SEPS), "s2": st.sampled_from(SEPS), "s3": st.sampled_from(SEPS),
    "tail": st.sampled_from(TAILS),
})


def _line(p: dict) -> str:
    if p["form"] == "node":
        return (f"{p['lead']}node {p['a']}{p['s1'] or ' '}C{p['s2']}={p['s3']}{p['num']}{p['s1']}{p['unit']}"
                f"{p['tail']}")
    return (f"{p['lead']}{p['kind']} {p['a']}{p['s1']}--{p['s2']}{p['b']}{p['s3']}={p['s1']}{p['num']} {p['unit']}"
            f"{p['tail']}")


CONTEXTS = [
    "{lines}",
    "param k = (1 W/K +\n{lines}\n)",
    "subnet cell(Cc)\n{lines}\nend",
    "subnet outer\nsubnet inner\nend\n{lines}\nend",
    "{lines}\nsubnet s\n  node q C = 1 J/K\nend\n{lines}",
]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(line_parts, min_size=1, max_size=6), st.sampled_from(CONTEXTS))
def test_simple_lines_read_as_the_parser_reads_them(parts, context):
    lines = "\n".join(_line(p) for p in parts)
    text = "network t\nunits temperature = degC\nboundary amb = 20 degC\n" + context.format(lines=lines) + "\n"
    assert _read(text, True) == _read(text, False), text


def test_plate_mesh_lines_all_take_the_simple_path_and_load_the_same_network():
    text = plate_thn(6, 5)
    taken, rest = split_simple_lines(text, "plate.thn", [])
    n_simple = sum(1 for ln in text.split("\n") if ln.startswith(("node ", "G ")))
    assert len(taken) == n_simple == 30 + (5 * 5 + 6 * 4) + 30
    assert not any(ln.startswith(("node ", "G ")) for ln in rest.split("\n"))
    assert _read(text, True) == _read(text, False)
    net = tnn_dsl.loads(text, "plate.thn")
    assert len(net.nodes) == 30 and len(net.links) == n_simple - 30


@pytest.mark.parametrize("line, why", [
    ("node free C = 1 J/K", "a keyword as a name"),
    ("node a C = 1 J/K \"label\"", "a label"),
    ("G a -- b = 1 W/K free", "a clause"),
    ("G a -- b = -1 W/K", "a sign"),
    ("G a -- b = 2 * 1 W/K", "an expression"),
    ("  node a C = (1 J/K", "an open bracket"),
    ("node a C = 1  free", "a clause where a unit could be (found by the property test)"),
    ("G a -- b = 2 as G_x", "a keyword where a unit could be"),
])
def test_lines_in_doubt_stay_with_the_parser(line, why):
    taken, rest = split_simple_lines(f"network t\n{line}\n", "t.thn", [])
    assert taken == [] and line in rest, why


def test_a_unit_error_on_a_simple_line_is_the_parsers_error():
    text = "network t\nboundary amb = 20 degC\nnode a C = 1 J/K\nG a -- amb = 1 W/Q\n"
    kind, diags = _read(text, True)
    assert kind == "error" and (kind, diags) == _read(text, False)
    assert diags[0][1].line == 4 and "W/Q" in diags[0][0]
