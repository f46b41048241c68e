"""The model doctor's extension as an IR edit (``tnn_dsl.doctor.extension``): every kind of accepted finding is
applied to the network with its fitted value, printed by ``print_thn``, and the written text parses back to an
IR holding exactly those findings (fast: no fitting, the fitted values are given)."""

from __future__ import annotations

import os

import pytest

import tnn_dsl
from tnn_dsl.doctor.candidates import build_extended
from tnn_dsl.doctor.extension import extend_network, extension_text, finding_clause
from tnn_dsl.ir import Input

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

NET = '''network two "two nodes"
units temperature = degC
input P : [W]
input Tamb : temperature
boundary amb = Tamb
node a C = 100 J/K
node b C = 200 J/K
G a -- amb = 1 W/K  free  as Ga
G b -- amb = 2 W/K
source a = P
sensor Sa = a
sensor Sb = b  column "Sb_degC"
'''

# (P only heats node a: a heat input, so Ga may depend on the temperatures it causes, not on P itself)
ACCEPTED = ["param_dependence:Ga:Tamb", "param_dependence:Ga:T(a)", "wrong_constant:G_b_amb:", "heat_load:Q[b]:",
            "unused_column:Q[a]:aux", "missing_link:a--b:", "radiation:a--amb:", "sensor_offset:Sb:"]
FITTED = {"G_dx_a_b": 0.0123456, "rad_dx_a_amb.area": 0.00123456, "Sb.offset": -0.345678}


def _setup():
    net = tnn_dsl.loads(NET, "two.thn")
    # as the doctor reads the data: an input for a column the network does not use (``aux``) and one it never
    # needs (``spare``)
    extra = [Input(name=n, column=n, dim={}, unit=None) for n in ("aux", "spare")]
    net_x = net.model_copy(update={"inputs": list(net.inputs) + extra}, deep=True)
    ext = build_extended(net_x, ["P", "Tamb"], ["aux", "spare"])
    cands = {c.key: c for c in ext.candidates}
    return net, net_x, [cands[k] for k in ACCEPTED]


def test_the_written_extension_holds_every_accepted_finding_with_its_fitted_value():
    net, net_x, accepted = _setup()
    extended = extend_network(net_x, accepted, FITTED, unused=[("aux", "aux"), ("spare", "spare")])
    text, diff = extension_text(net, extended, accepted, "two.thn")
    back = tnn_dsl.loads(text, "extended.thn")
    assert text.startswith("# two (two.thn) extended by `tnnc diagnose`") and "#   offset on sensor Sb" in text
    # learned functions: merged per target, grouped by input set; the user's values are untouched
    fns = {tuple(t.name for t in fn.targets): fn for fn in back.learned}
    assert set(fns) == {("Ga",), ("G_b_amb", "b"), ("a",)}
    assert fns[("Ga",)].kind == "linear" and [(i.kind, i.name) for i in fns[("Ga",)].inputs] == [
        ("input", "Tamb"), ("node", "a")]
    assert fns[("G_b_amb", "b")].kind == "const"
    assert [t.kind for t in fns[("G_b_amb", "b")].targets] == ["param", "heat_load"]
    assert fns[("a",)].kind == "linear" and [i.name for i in fns[("a",)].inputs] == ["aux"]
    assert back.param("Ga").value == 1.0 and back.param("G_b_amb").value == 2.0
    # the new input (only the column a finding reads), link, radiation and offset, at their fitted values
    assert [(i.name, i.column) for i in back.inputs] == [("P", "P"), ("Tamb", "Tamb"), ("aux", "aux")]
    link = next(lk for lk in back.links if {lk.a, lk.b} == {"a", "b"})
    g = back.param(link.value)
    assert (link.form, link.name, g.value, g.free, g.unit) == ("G", "G_a_b", 0.01235, True, "W/K")
    (rad,) = back.radiations
    assert (rad.name, rad.a, rad.b) == ("rad_a_amb", "a", "amb")
    assert back.param(rad.area).value == pytest.approx(0.001235, rel=1e-12) and back.param(rad.area).free
    assert back.param(rad.emissivity).value == 1.0 and back.param(rad.view_factor).value == 1.0
    sb = next(s for s in back.sensors if s.name == "Sb")
    assert sb.column == "Sb_degC" and back.param(sb.offset).value == -0.3457 and back.param(sb.offset).free
    # the diff shows only the change
    removed = [ln for ln in diff.splitlines() if ln.startswith("-") and not ln.startswith("---")]
    assert removed == ['-sensor Sb = b  column "Sb_degC"']
    assert "+learn Ga as linear(Tamb, a)" in diff and "+learn G_b_amb, Q[b] as const" in diff
    assert "+G a -- b = 0.01235 W/K  free" in diff and "+radiation a -- amb  area = 0.001235 m^2  free" in diff


def test_a_findings_clause_is_its_printed_change():
    net, net_x, accepted = _setup()
    by_key = {c.key: c for c in accepted}
    assert finding_clause(net_x, by_key["missing_link:a--b:"], FITTED) == "G a -- b = 0.01235 W/K  free"
    assert finding_clause(net_x, by_key["sensor_offset:Sb:"], FITTED) == (
        'sensor Sb = b  offset -0.3457 K  free  column "Sb_degC"')
    assert finding_clause(net_x, by_key["param_dependence:Ga:T(a)"], FITTED) == "learn Ga as linear(a)"


def test_a_learned_constant_that_depends_on_something_keeps_its_other_targets():
    net = tnn_dsl.load(os.path.join(ROOT, "networks", "peltier_heatpipe", "m1.thn"))
    ext = build_extended(net, ["I", "u1"], [])
    cand = next(c for c in ext.candidates if c.key == "param_dependence:R_hp1:u1")
    text, _ = extension_text(net, extend_network(net, [cand], {}), [cand])
    assert "learn R_hp2, R_hpa as const\n" in text and "learn R_hp1 as linear(u1)\n" in text
    back = tnn_dsl.loads(text, "m1x.thn")
    assert sorted(back.learned_targets()) == ["R_hp1", "R_hp2", "R_hpa"]
