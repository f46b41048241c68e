"""The model doctor's "heat capacity behind a source" candidate (``source_mass``; Bacher & Madsen's TiTh step):
the source heats a new node joined to its node by a resistance, instead of heating the node directly.

* candidates exist for sources driven by inputs (not for constant heat loads);
* the edit (``_candidates.apply_structural``) keeps the steady state and changes the transients;
* ``_candidates.source_lag_forcing`` is the heat that really reaches the node in a simulation of the edited
  network (node held nearly constant by a huge capacity, so the exact ODE is the pure lag), both backends;
* the printed extension (new node, its link, the source moved) re-loads to the same simulation.
"""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler.model import compile as _compile
from tnn_dsl.doctor.extension import extend_network
from tnn_dsl.doctor.forcing import source_lag_forcing, source_tau_grid
from tnn_dsl.doctor.structural import (
    apply_structural,
    source_mass_values,
    structural_candidates,
)
from tnn_dsl.lang import print_thn
from tnn_dsl.studies.planted import step_inputs

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
TCLAB = os.path.join(HERE, "hidden_nets", "tclab_board.thn")
BUILDING = os.path.join(HERE, "hidden_nets", "building_ti.thn")
K0 = 273.15
BACKENDS = ["jax", "torch"]


def _cands(net):
    return {c.key: c for c in structural_candidates(net, ("source_mass",))}


def _sim(net, u, dt, backend="numpy", states=False):
    m = _compile(net, backend=backend, dtype="float64")
    p = m.init_params()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        x, y = m.rollout(p, m.steady_state(p, u[0]), u, dt)
    x, y = (np.asarray(m.xp.to_numpy(a), dtype=float) for a in (x, y))
    return (x, y, m) if states else y


def test_candidates_for_input_driven_sources_only():
    net = tnn_dsl.load(BUILDING)
    keys = set(_cands(net))
    assert keys == {"source_mass:Q_solar:", "source_mass:Q_heat:"}
    c = _cands(net)["source_mass:Q_heat:"]
    assert c.k == 2 and [col.key for col in c.columns] == ["C_m_Q_heat", "R_m_Q_heat"]
    assert c.element["at"] == "ti" and c.element["node"] == "m_Q_heat"
    assert "behind source Q_heat" in c.describe()
    # a constant heat load has no candidate: a lag behind a constant is invisible
    text = open(BUILDING, encoding="utf-8").read() + "\nsource ti = 100 W  as Q_base\n"
    assert "source_mass:Q_base:" not in _cands(tnn_dsl.loads(text, "b.thn"))
    tc = _cands(tnn_dsl.load(TCLAB))
    assert set(tc) == {"source_mass:Q_src_h1:", "source_mass:Q_src_h2:"}


def test_the_edit_keeps_the_steady_state_and_changes_transients():
    net = tnn_dsl.load(BUILDING)
    c = _cands(net)["source_mass:Q_heat:"]
    edited = apply_structural(net, c, 1.8e6, lower=1e3, resistance=1e-3, resistance_lower=1e-6)
    assert [n.name for n in edited.nodes] == ["ti", "m_Q_heat"]
    assert {s.name: s.node for s in edited.sources} == {"Q_solar": "ti", "Q_heat": "m_Q_heat"}
    assert edited.param("C_m_Q_heat").free and edited.param("R_m_Q_heat").free
    m0, m1 = _compile(net, backend="numpy"), _compile(edited, backend="numpy")
    u = np.array([K0 + 2.0, 300.0, 3000.0])
    p0, p1 = m0.init_params(), m1.init_params()
    np.testing.assert_allclose(m1.outputs(p1, m1.steady_state(p1, u), u), m0.outputs(p0, m0.steady_state(p0, u), u),
                               atol=1e-8)
    rng = np.random.default_rng(0)
    U = step_inputs(rng, 400, {"Ta": (K0 - 5, K0 + 10), "Ps": (0, 600), "Ph": (0, 4000)}, net.input_names, (12, 72))
    assert np.max(np.abs(_sim(edited, U, 300.0) - _sim(net, U, 300.0))) > 0.1
    with pytest.raises(ValueError, match="resistance"):
        apply_structural(net, c, 1.8e6)


@pytest.mark.parametrize("backend", BACKENDS)
def test_lag_forcing_is_the_heat_that_reaches_the_node(backend):
    """With the node's capacity huge, its temperature barely moves and the heat through the new link obeys
    τ·dQ_h/dt = Q − Q_h exactly: the forcing's start-of-interval values are Q_h − Q of the simulation."""
    text = open(BUILDING, encoding="utf-8").read().replace("C = 2.9 kWh/K", "C = 1e9 kWh/K")
    net = tnn_dsl.loads(text, "b.thn")
    assert net.param(net.nodes[0].capacitance).value > 1e12
    c = _cands(net)["source_mass:Q_heat:"]
    dt, tau, cap = 300.0, 3000.0, 1.0e6
    edited = apply_structural(net, c, cap, resistance=tau / cap)
    U = step_inputs(np.random.default_rng(1), 300, {"Ta": (K0 - 5, K0 + 10), "Ps": (0, 600), "Ph": (0, 4000)},
                    net.input_names, (3, 30))
    X, _, m = _sim(edited, U, dt, backend=backend, states=True)
    names = list(m.state_names)
    q_h = (X[:, names.index("m_Q_heat")] - X[:, names.index("ti")]) / (tau / cap)  # W into ti
    q = U[:, net.input_names.index("Ph")]
    F = source_lag_forcing(net, c, X[:, :1], U, {}, [len(U)], [dt], tau)
    assert F.shape == (len(U), 1)
    # the forcing is the interval mean of Q_h − Q; the start value follows from it exactly
    e = math.exp(-dt / tau)
    start = F[:, 0] / ((tau / dt) * (1 - e)) + q
    np.testing.assert_allclose(start, q_h, atol=1e-6 * 4000)
    assert np.max(np.abs(F)) > 100.0  # W: the lag is visible


def test_lines_and_moved_source_reload_to_the_same_simulation():
    net = tnn_dsl.load(BUILDING)
    c = _cands(net)["source_mass:Q_heat:"]
    edited = apply_structural(net, c, 1.8e6, resistance=1e-3)
    m = _compile(edited, backend="numpy")
    p = m.to_numpy(m.init_params())
    v = source_mass_values(edited, c, p)
    assert v["C"] == pytest.approx(1.8e6) and v["R"] == pytest.approx(1e-3) and v["tau"] == pytest.approx(1800.0)
    lines = print_thn(extend_network(edited, [c], p)).splitlines()
    node = next(ln for ln in lines if ln.startswith("node m_Q_heat "))
    assert "C = 0.5 kWh/K" in node and "free" in node  # the heated node's unit
    assert "R m_Q_heat -- ti = 1 K/kW  free  as R_m_Q_heat" in lines  # the file's resistance unit
    assert "source m_Q_heat = Ph  as Q_heat" in lines  # the source moved to the new node
    new = tnn_dsl.loads("\n".join(lines) + "\n", "extended.thn")
    U = step_inputs(np.random.default_rng(2), 200, {"Ta": (K0 - 5, K0 + 10), "Ps": (0, 600), "Ph": (0, 4000)},
                    net.input_names, (12, 72))
    np.testing.assert_allclose(_sim(new, U, 300.0), _sim(edited, U, 300.0), atol=1e-9)


def test_tau_grid():
    g = source_tau_grid(300.0, 300.0 * 1000)
    assert g[0] == 150.0 and all(b == pytest.approx(3 * a) for a, b in zip(g, g[1:])) and g[-1] <= 1e5


def test_doctor_names_the_heater_mass_and_writes_the_moved_source():
    """End to end on the suite's building case (B&M's Ti with a 0.5 kWh/K heater mass behind 1 K/kW planted):
    the first answer is the capacity behind Q_heat, its C and R are recovered, and the extension moves the
    source line to the new node and re-loads."""
    import importlib.util
    import sys

    spec = importlib.util.spec_from_file_location("diagnose_suite",
                                                  os.path.join(ROOT, "benchmarks", "diagnose_suite.py"))
    S = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("diagnose_suite", S)
    spec.loader.exec_module(S)
    case = next(c for c in S.CASES if c.name == "building/source_mass")
    net, tr, va = S.make_data(case, 0.01, 0, True, None)
    d = tnn_dsl.diagnose(net, tr, va, top=3, max_rounds=1, mlp_check=False)
    first = d.accepted[0]
    assert first.kind == "source_mass" and first.target == "Q_heat", d.summary()
    assert "m_Q_heat" in first.words and "1.8e+06 J/K" in first.words, first.words
    assert "source m_Q_heat = Ph  as Q_heat" in d.extended_text
    new = tnn_dsl.loads(d.extended_text, "extended.thn")
    assert {s.name: s.node for s in new.sources}["Q_heat"] == "m_Q_heat"
    assert d.extended["val_mae"] < 0.1 * d.baseline["val_mae"]
