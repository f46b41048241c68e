"""Per-experiment parameters in the language and the IR (issue 15): `free [in [LO, HI]] per experiment` on
every slot that may be free, ``Param.per_experiment`` in the IR and its JSON, the printer, the equations and
`tnnc check`, the validation errors (each with its position) and networks/tclab/tclab_ambient.thn."""

from __future__ import annotations

import csv
import logging
import os

import pytest
from lark import Lark
from lark import logger as lark_logger

import tnn_dsl
from tnn_dsl import TnnError
from tnn_dsl.cli import main
from tnn_dsl.ir import Network, Num
from tnn_dsl.ir.emit import equations, ir_json, network_from_json
from tnn_dsl.lang import print_thn, validate
from tnn_dsl.lang.grammar import _grammar_text, _Newlines

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
AMBIENT = os.path.join(ROOT, "networks", "tclab", "tclab_ambient.thn")
DATA = os.path.join(os.path.dirname(ROOT), "shared", "data")

HEAD = """network n
units temperature = degC
input Q1 : [%]
boundary amb = Ta
node h1 C = 4 J/K free
source h1 = 0.01 W/% * Q1
"""

EVERY_SLOT = HEAD + """param Ta = 23 degC free in [15 degC, 30 degC] per experiment  "ambient"
param g0 = 0.05 W/K free per experiment
node h2 C = 4 J/K free per experiment
G h1 -- amb = g0 as U1
G h2 -- amb = 0.05 W/K free per experiment as U2
R h1 -- h2 = 10 K/W per experiment free
radiation h1 -- amb  area = 1e-3 m^2 free per experiment  emissivity = 0.9 free in [0.5, 1] per experiment
fluid f1 through h2  inlet = 20 degC free per experiment  mdot = 2 g/s  cp = 4186 J/(kg*K)  UA = 5 W/K
peltier pe  hot = h1  cold = h2  current = 1 A free per experiment  seebeck = 0.05 V/K  resistance = 2 ohm
sensor T1 = h1  lag 20 s free per experiment  offset 0 K free in [-1 K, 1 K] per experiment  column "T1_degC"
sensor T2 = h2
"""

PER = {"Ta", "g0", "C_h2", "U2", "R_h1_h2", "rad_h1_amb.area", "rad_h1_amb.emissivity", "f1.inlet", "pe.current",
       "T1.lag", "T1.offset"}


def _errors(text: str) -> list[str]:
    """The ``line:col: message`` of each error of ``text`` (parsed as ``x.thn``)."""
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(text, "x.thn")
    return [f"{d.span.line}:{d.span.col}: {d.message}" for d in info.value.diagnostics]


def _ir(net: Network) -> dict:
    def strip(x):
        if isinstance(x, dict):
            return {k: strip(v) for k, v in x.items() if k not in ("span", "source_files")}
        if isinstance(x, list):
            return [strip(v) for v in x]
        return x

    return strip(net.model_dump())


# -- the grammar ------------------------------------------------------------------------------------------------


def test_the_grammar_has_no_lalr_conflicts():
    messages: list[str] = []

    class _Collect(logging.Handler):
        def emit(self, record):
            messages.append(record.getMessage())

    handler = _Collect()
    level = lark_logger.level
    lark_logger.addHandler(handler)
    lark_logger.setLevel(logging.DEBUG)
    try:
        Lark(_grammar_text(), parser="lalr", lexer="contextual", propagate_positions=True,
             maybe_placeholders=False, postlex=_Newlines(), debug=True)
    finally:
        lark_logger.removeHandler(handler)
        lark_logger.setLevel(level)
    assert not [m for m in messages if "conflict" in m.lower()]


def test_every_free_slot_may_be_per_experiment():
    net = tnn_dsl.loads(EVERY_SLOT, "x.thn")
    assert {p.name for p in net.params if p.per_experiment} == PER
    for name in PER:
        p = net.param(name)
        assert p.free and isinstance(p.expr, Num)
    ta = net.param("Ta")
    assert ta.lower == pytest.approx(288.15) and ta.upper == pytest.approx(303.15) and ta.label == "ambient"
    assert not net.param("C_h1").per_experiment and not net.param("pe.seebeck").per_experiment
    assert not net.param("T_amb").per_experiment  # a boundary has no `free`, hence no `per experiment`


def test_the_default_is_not_per_experiment():
    net = tnn_dsl.load(os.path.join(ROOT, "networks", "tclab", "tclab.thn"))
    assert not any(p.per_experiment for p in net.params)
    assert "per_experiment" in type(net.params[0]).model_fields


# -- IR, JSON, printer, equations, check --------------------------------------------------------------------------


def test_json_round_trip_keeps_the_flag():
    net = tnn_dsl.loads(EVERY_SLOT, "x.thn")
    text = ir_json(net)
    assert '"per_experiment": true' in text
    back = network_from_json(text)
    assert back == Network.from_json(net.to_json())
    assert {p.name for p in back.params if p.per_experiment} == PER
    assert ir_json(back) == text
    old = text.replace('"per_experiment": false,', "").replace('"per_experiment": true,', "")
    assert not any(p.per_experiment for p in network_from_json(old).params)  # files written before: default


def test_printer_round_trip_keeps_the_flag():
    net = tnn_dsl.loads(EVERY_SLOT, "x.thn")
    text = print_thn(net)
    for line in ('param Ta = 23 degC  free in [15 degC, 30 degC] per experiment  "ambient"',
                 "node h2  C = 4 J/K  free per experiment", "G h2 -- amb = 0.05 W/K  free per experiment  as U2",
                 "R h1 -- h2 = 10 K/W  free per experiment", "offset 0 K  free in [-1 K, 1 K] per experiment"):
        assert line in text
    back = tnn_dsl.loads(text, "printed.thn")
    assert _ir(back) == _ir(net)
    assert print_thn(back) == text


def test_equations_and_check_show_per_experiment(tmp_path, capsys):
    net = tnn_dsl.loads(EVERY_SLOT, "x.thn")
    eq = equations(net)
    assert "Ta = 296.15 K   (free in [288.15, 303.15] K; per experiment;" in eq
    assert "T1.offset = 0 K   (free in [-1, 1] K; per experiment)" in eq
    assert "C_h1 = 4 J/K   (free; positive)" in eq
    path = tmp_path / "x.thn"
    path.write_text(EVERY_SLOT)
    assert main(["check", str(path)]) == 0
    out = capsys.readouterr().out
    assert "Ta (per experiment)" in out and "C_h1," in out
    assert f"of which {len(PER)} per experiment" in out
    assert main(["compile", str(path)]) == 0
    assert "(free; per experiment; positive)" in capsys.readouterr().out


# -- validation errors ------------------------------------------------------------------------------------------


def test_per_experiment_without_free():
    errs = _errors(HEAD + "param Ta = 23 degC per experiment\nG h1 -- amb = 1 W/K per experiment\n"
                   "sensor T1 = h1  lag 20 s per experiment\n")
    assert errs == ["7:20: a per-experiment value must be free: write `free per experiment`",
                    "8:21: a per-experiment value must be free: write `free per experiment`",
                    "9:26: a per-experiment value must be free: write `free per experiment`"]


def test_per_experiment_on_a_derived_parameter():
    errs = _errors(HEAD + "param Ta = 23 degC\nparam k = 2 * Ta per experiment\nparam k2 = 3 W/K\n"
                   "G h1 -- amb = k2 * 2 free per experiment\nsensor T1 = h1\n")
    assert errs == ["8:1: `k` is an expression and cannot be `per experiment`",
                    "10:1: `G_h1_amb` is an expression and cannot be `free`",
                    "10:1: `G_h1_amb` is an expression and cannot be `per experiment`"]


def test_per_experiment_on_a_learned_parameter():
    text = HEAD + "param Ta = 23 degC free per experiment\nG h1 -- amb = 1 W/K free per experiment as U1\n" \
        "sensor T1 = h1\nlearn U1 as linear(h1)\n"
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(text, "x.thn")
    (d,) = info.value.diagnostics
    assert (d.span.line, d.span.col, d.message) == (10, 7, "cannot learn `U1`: it is `per experiment`")
    assert d.related[0][1].line == 8
    assert "drop `per experiment`" in (d.hint or "")


def test_every_problem_is_reported_together():
    errs = _errors(HEAD + "param Ta = 23 degC per experiment\nparam k = 2 * Ta per experiment\n"
                   "node h2 C = -1 J/K\nG h2 -- amb = 1 W/K\nsensor T1 = h1\n")
    assert errs == ["7:20: a per-experiment value must be free: write `free per experiment`",
                    "8:1: `k` is an expression and cannot be `per experiment`",
                    "9:13: the capacity of node `h2` must be positive, got -1 (SI; written in J/K)"]


def test_validate_refuses_an_ir_edit_without_free():
    net = tnn_dsl.load(os.path.join(ROOT, "networks", "tclab", "tclab.thn"))
    params = [p.model_copy(update={"per_experiment": True, "free": False}) if p.name == "a1" else p
              for p in net.params]
    with pytest.raises(TnnError, match="a per-experiment value must be free"):
        validate(net.model_copy(update={"params": params}))


@pytest.mark.parametrize("clause, col, message", [
    ("per experiment free", 35, "`free` comes before `per experiment`"),
    ("free per experiment in [15 degC, 30 degC]", 40, "`in [LOW, HIGH]` comes before `per experiment`"),
    ("free per experiments", 39, "expected a label or the end of the clause after `per experiment`, found `s`"),
    ("free per file", 29, "expected `experiment` after `per`, found `file`"),
    ("free per run", 29, "expected `experiment` after `per`, found `run`"),
    ("free per", 28, "expected `experiment` after `per`, found end of line"),
    ("free perexperiment", 25, "`per` and `experiment` are two words"),
])
def test_misspelt_clauses(clause, col, message):
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(HEAD + f"param Ta = 23 degC {clause}\nsensor T1 = h1\n", "x.thn")
    d = info.value.diagnostics[0]
    assert (d.span.line, d.span.col, d.message) == (7, col, message)
    assert "per experiment" in (d.hint or "")


def test_misspelt_clauses_on_a_sensor_offset():
    with pytest.raises(TnnError) as info:
        tnn_dsl.loads(HEAD + "param Ta = 23 degC\nsensor T1 = h1  offset 0 K per experiment free\n", "x.thn")
    d = info.value.diagnostics[0]
    assert (d.span.line, d.span.col, d.message) == (8, 43, "`free` comes before `per experiment`")


# -- the network ------------------------------------------------------------------------------------------------


def test_tclab_ambient_is_tclab_with_a_per_experiment_ambient(capsys):
    base = tnn_dsl.load(os.path.join(ROOT, "networks", "tclab", "tclab.thn"))
    net = tnn_dsl.load(AMBIENT)
    assert [p.name for p in net.params if p.per_experiment] == ["Ta"]
    ta = net.param("Ta")
    assert ta.free and (ta.lower, ta.upper) == (pytest.approx(288.15), pytest.approx(303.15))
    # apart from the flag, the names and labels, the same network
    flat = net.model_copy(update={"params": [p.model_copy(update={"per_experiment": False}) for p in net.params],
                                  "name": base.name, "label": base.label})
    assert _ir(flat) == _ir(base)
    assert main(["check", AMBIENT]) == 0
    assert "Ta (per experiment)" in capsys.readouterr().out
    with open(AMBIENT, encoding="utf-8") as f:
        head = f.read().split("\nnetwork ", 1)[0]
    assert "README.md" in head and "per experiment" in head and "APMonitor" in head


@pytest.mark.parametrize("data", ["tclab_kuntz_rawlings_prbs_openloop.csv", "tclab_apmonitor_energy_balance_steps.csv"])
def test_tclab_ambient_columns_exist_in_the_real_data(data):
    path = os.path.join(DATA, data)
    if not os.path.isfile(path):
        pytest.skip(f"{path} is not in this checkout")
    with open(path, encoding="utf-8") as f:
        header = next(csv.reader(f))
    net = tnn_dsl.load(AMBIENT)
    assert {i.column for i in net.inputs} | {s.column for s in net.sensors} <= set(header)
