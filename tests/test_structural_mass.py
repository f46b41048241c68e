"""The model doctor's missing-thermal-mass candidate (issue 6): a new node between a node and its neighbour or
boundary, the link split in two with the same total resistance.

* the edit (``_candidates.apply_structural``) keeps the steady state and changes the transients;
* the score-test column (``_candidates.mass_forcing`` pushed through the forced Jacobian) is the derivative of a
  real simulation of the edited network w.r.t. the mass (Richardson-extrapolated finite difference), for a
  node–boundary link, a node–node link and a boundary driven by a stepped input; the finite-mass column is
  closer to the real effect of a large mass than the first-order one;
* the extension (the edit with its fitted values, printed by ``print_thn``) re-loads to the same simulation
  (file units kept);
* end to end, ``tnn_dsl.diagnose`` names ``thermal_mass:h1--amb`` first on the suite's TCLab case and writes a
  valid extension with the new node.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import warnings

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler.model import compile as _compile
from tnn_dsl.data import Experiment
from tnn_dsl.doctor.base import MASS_FRACTION_BOUNDS
from tnn_dsl.doctor.candidates import build_extended
from tnn_dsl.doctor.extension import extend_network, extension_text
from tnn_dsl.doctor.forcing import mass_forcing, mass_grid
from tnn_dsl.doctor.structural import apply_structural, structural_candidates
from tnn_dsl.lang import print_thn
from tnn_dsl.studies.planted import step_inputs

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
TCLAB = os.path.join(HERE, "hidden_nets", "tclab_board.thn")
BUILDING = os.path.join(HERE, "hidden_nets", "building_ti.thn")
CASESTUDY = os.path.join(ROOT, "networks", "peltier_heatpipe", "nominal.thn")
K0 = 273.15
BACKENDS = ["jax", "torch"]


def _cand(net, key):
    return next(c for c in structural_candidates(net) if c.key == key)


def _sim(net, u, dt, backend="numpy"):
    """Outputs (N, n_out) K from the steady state of u[0] (RK4, automatic sub-steps)."""
    m = _compile(net, backend=backend, dtype="float64")
    p = m.init_params()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _, y = m.rollout(p, m.steady_state(p, u[0]), u, dt)
    return np.asarray(m.xp.to_numpy(y), dtype=float)


# ---------------------------------------------------------------------------------------------
# the candidates and the edit
# ---------------------------------------------------------------------------------------------


def test_one_candidate_per_constant_link_named_as_the_suite_names_them():
    keys = {c.key for c in structural_candidates(tnn_dsl.load(TCLAB))}
    assert {"thermal_mass:h1--amb:", "thermal_mass:h2--amb:", "thermal_mass:h1--h2:"} <= keys
    assert "thermal_mass:ti--amb:" in {c.key for c in structural_candidates(tnn_dsl.load(BUILDING))}
    cs = [c for c in structural_candidates(tnn_dsl.load(CASESTUDY)) if c.kind == "thermal_mass"]
    assert len(cs) == 9  # every R link of the case study
    assert "thermal_mass:hx2--hp:" in {c.key for c in cs}  # the sensed node first (T_out reads hx2)
    c = next(c for c in cs if c.target == "hx2--hp")
    assert c.k == 2 and [col.key for col in c.columns] == ["C_m_hx2_hp", "f_m_hx2_hp"]
    # a nonlinear network (Peltier, fluids): the split keeps its steady state too (numpy reference backend)
    net = tnn_dsl.load(CASESTUDY)
    u = np.array([1.5, 0.5, K0 + 22, K0 + 25, K0 + 25])
    m0 = _compile(net, backend="numpy")
    m1 = _compile(apply_structural(net, c, 250.0, frac=0.3), backend="numpy")
    p0, p1 = m0.init_params(), m1.init_params()
    np.testing.assert_allclose(m1.outputs(p1, m1.steady_state(p1, u), u), m0.outputs(p0, m0.steady_state(p0, u), u),
                               atol=1e-8)
    # only thermal masses if asked
    assert all(c.kind == "thermal_mass" for c in structural_candidates(tnn_dsl.load(TCLAB), ("thermal_mass",)))


def test_learned_and_derived_links_are_not_split():
    text = open(TCLAB, encoding="utf-8").read()
    text = text.replace("G h1 -- h2  = 0.01 W/K  as U12", "G h1 -- h2  = 0.0005 W/K^2 * (T(h1) - 10 degC)  as U12")
    text += "\nlearn U2 as const\n"
    net = tnn_dsl.loads(text, "derived.thn")
    targets = {c.target for c in structural_candidates(net) if c.kind == "thermal_mass"}
    assert targets == {"h1--amb"}  # U12 derived, U2 learned


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("path,key", [(TCLAB, "thermal_mass:h1--amb:"), (TCLAB, "thermal_mass:h1--h2:"),
                                      (BUILDING, "thermal_mass:ti--amb:")], ids=["boundary", "node", "building"])
def test_the_split_keeps_the_steady_state(backend, path, key):
    net = tnn_dsl.load(path)
    cand = _cand(net, key)
    m0 = _compile(net, backend=backend, dtype="float64")
    p0 = m0.init_params()
    rng = np.random.default_rng(0)
    for frac in (0.2, 0.9):
        cap = 5.0 * float(net.param(net.nodes[0].capacitance).value)
        edited = apply_structural(net, cand, cap, frac=frac)
        assert edited.node_names[-1] == cand.element["node"] and len(edited.links) == len(net.links) + 1
        m1 = _compile(edited, backend=backend, dtype="float64")
        p1 = m1.init_params()
        for _ in range(3):
            u = np.array([K0 + rng.uniform(0, 30) if i.is_temperature else rng.uniform(0, 1) for i in net.inputs])
            s0 = np.asarray(m0.outputs(p0, m0.steady_state(p0, u), u), dtype=float)
            s1 = np.asarray(m1.outputs(p1, m1.steady_state(p1, u), u), dtype=float)
            np.testing.assert_allclose(s1, s0, atol=1e-7)
    # the fraction is bounded, the mass free and positive
    f = edited.param(cand.element["frac"])
    assert f.free and (f.lower, f.upper) == MASS_FRACTION_BOUNDS
    cm = edited.param(cand.element["param"])
    assert cm.free and cm.role == "capacitance" and cm.value == pytest.approx(cap)


def test_the_edit_changes_transients():
    net = tnn_dsl.load(TCLAB)
    u = step_inputs(np.random.default_rng(1), 600, {"Q1": (0, 1), "Q2": (0, 1)}, net.input_names, (60, 300))
    y0 = _sim(net, u, 1.0)
    y1 = _sim(apply_structural(net, _cand(net, "thermal_mass:h1--amb:"), 3.0), u, 1.0)
    assert np.max(np.abs(y1 - y0)) > 0.1


# ---------------------------------------------------------------------------------------------
# the score-test column
# ---------------------------------------------------------------------------------------------

_CASES = {
    "tclab-boundary": (TCLAB, {"Q1": (0, 1), "Q2": (0, 1)}, 1.0, (60, 300), "thermal_mass:h1--amb:", 0.02, 3.0),
    "tclab-node": (TCLAB, {"Q1": (0, 1), "Q2": (0, 1)}, 1.0, (60, 300), "thermal_mass:h1--h2:", 0.02, 3.0),
    # the outdoor temperature is a stepped input: the boundary's rate is an impulse per step
    "building-input": (BUILDING, {"Ta": (K0 - 5, K0 + 10), "Ps": (0, 600), "Ph": (0, 4000)}, 300.0, (12, 72),
                       "thermal_mass:ti--amb:", 4e4, 1.37e7),
}


def _engine(net, u, dt, backend):
    from tnn_dsl.doctor.engine import _make_engine, _split_masks, _State

    n = u.shape[0]
    y = _sim(net, u, dt)
    exp = Experiment(name="t", path="<t>", t=np.arange(n) * dt, dt=dt, inputs=u, outputs=y,
                     input_names=tuple(net.input_names), output_names=tuple(s.name for s in net.sensors))
    exps, tm, vm = _split_masks([exp], [])
    ext0 = build_extended(net, [], kinds=("sensor_offset",), only=set())
    eng, _, _, _ = _make_engine(ext0, net, exps, tm, vm, backend, _State(), {}, [])
    return eng, y


def _setup(case, seed, backend):
    """One case of ``_CASES`` ready to compare: (network, inputs (500, n_in), dt, engine, nominal outputs,
    the mass candidate, (finite-difference step, large mass))."""
    path, bounds, dt, hold, key, eps, big = _CASES[case]
    net = tnn_dsl.load(path)
    u = step_inputs(np.random.default_rng(seed), 500, bounds, net.input_names, hold)
    eng, y0 = _engine(net, u, dt, backend)
    return net, u, dt, eng, y0, _cand(net, key), (eps, big)


def _column(eng, cand, u, dt, mass=None):
    """The candidate's score column: d y[train rows] / d C_m (K per J/K)."""
    _, X = eng.simulate()
    X = X[: eng.n_score_rows]
    F = mass_forcing(eng.net, cand, X, u, eng.params, [u.shape[0]], [dt], rates=eng.rates(X, u), mass=mass)
    return eng.forced_jacobian([], F[None, :, : eng.n_force])[:, 0]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", sorted(_CASES))
def test_score_column_is_the_derivative_of_a_real_simulation(backend, case):
    net, u, dt, eng, y0, cand, (eps, _) = _setup(case, 3, backend)
    col = _column(eng, cand, u, dt)

    def fd(c):
        return (_sim(apply_structural(net, cand, c), u, dt) - y0).ravel()[eng.train_idx] / c

    d1, d2 = fd(eps), fd(eps / 2)
    rich = 2 * d2 - d1  # the finite difference's own first-order error removed
    assert np.linalg.norm(rich) > 0
    err = np.linalg.norm(col - rich) / np.linalg.norm(rich)
    assert err < 5e-3, err
    # and the plain finite difference converges to it (the error halves with the step)
    e1 = np.linalg.norm(col - d1) / np.linalg.norm(d1)
    e2 = np.linalg.norm(col - d2) / np.linalg.norm(d2)
    assert e2 < 0.7 * e1 or e2 < 5e-3


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", sorted(_CASES))
def test_finite_mass_column_follows_a_large_mass_better_than_first_order(backend, case):
    net, u, dt, eng, y0, cand, (_, big) = _setup(case, 4, backend)
    real = (_sim(apply_structural(net, cand, big), u, dt) - y0).ravel()[eng.train_idx] / big
    lagged = _column(eng, cand, u, dt, mass=big)
    first = _column(eng, cand, u, dt)
    e_lag = np.linalg.norm(lagged - real) / np.linalg.norm(real)
    e_first = np.linalg.norm(first - real) / np.linalg.norm(real)
    assert e_lag < 0.25 and e_lag < 0.3 * e_first, (e_lag, e_first)
    # the grid of masses tried covers the planted one within a factor of 3
    grid = mass_grid(net, cand, eng.params, dt, u.shape[0] * dt)
    assert grid and min(abs(np.log(g / big)) for g in grid) <= np.log(3) + 1e-9


# ---------------------------------------------------------------------------------------------
# the extension text
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("path,key,cap,unit", [(TCLAB, "thermal_mass:h1--h2:", 2.5, "J/K"),
                                               (BUILDING, "thermal_mass:ti--amb:", 1.2e7, "kWh/K"),
                                               (CASESTUDY, "thermal_mass:hx2--hp:", 250.0, "J/K")],
                         ids=["tclab", "building", "casestudy"])
def test_extension_text_round_trips_through_the_parser(backend, path, key, cap, unit):
    import re

    net = tnn_dsl.load(path)
    cand = _cand(net, key)
    edited = extend_network(apply_structural(net, cand, cap, frac=0.37), [cand], {})
    text = print_thn(edited)
    node_line = next(ln for ln in text.splitlines() if ln.startswith(f"node {cand.element['node']} "))
    assert re.search(rf"C = [0-9.e+-]+ {re.escape(unit)}\s+free", node_line), node_line
    reloaded = tnn_dsl.loads(text, "extended.thn")
    assert reloaded.node_names == edited.node_names
    assert {l.name for l in reloaded.links} == {l.name for l in edited.links}
    assert reloaded.param(cand.element["frac"]).free and reloaded.param(cand.element["param"]).free
    bounds = {i.name: ((K0 + 10, K0 + 25) if i.is_temperature else (0.0, 1.0)) for i in net.inputs}
    dt = 300.0 if path == BUILDING else 1.0
    u = step_inputs(np.random.default_rng(5), 200, bounds, net.input_names, (10, 40))
    np.testing.assert_allclose(_sim(reloaded, u, dt, backend), _sim(edited, u, dt, backend), atol=1e-8)


def test_extension_splits_the_link_with_the_fitted_values():
    net = tnn_dsl.load(TCLAB)
    cand = _cand(net, "thermal_mass:h1--amb:")
    edited = apply_structural(net, cand, 3.0, frac=0.45)
    params = {k: np.asarray(v) for k, v in _compile(edited, backend="numpy").init_params().items()}
    params[cand.element["param"]], params[cand.element["frac"]] = np.asarray(2.7182818), np.asarray(0.3141592)
    new, diff = extension_text(net, extend_network(edited, [cand], params), [cand])
    assert 'node m_h1_amb "thermal mass found by the model doctor"  C = 2.71828 J/K  free\n' in new  # 6 digits
    assert "param f_m_h1_amb = 0.3142  free in [0.05, 0.95]" in new
    assert "-G h1 -- amb = 0.02 W/K  as U1\n" in diff
    assert '+param U1 = 0.02 W/K  "total of the links h1–m_h1_amb–amb"\n' in diff
    assert "+G h1 -- m_h1_amb = U1 / f_m_h1_amb\n" in diff and "+G m_h1_amb -- amb = U1 / (1 - f_m_h1_amb)\n" in diff
    reloaded = tnn_dsl.loads(new, "extended.thn")
    assert "m_h1_amb" in reloaded.node_names and "U1" not in {l.name for l in reloaded.links}
    assert reloaded.param("C_m_h1_amb").value == 2.71828 and reloaded.param("f_m_h1_amb").free


# ---------------------------------------------------------------------------------------------
# end to end on the hidden-effect suite's TCLab case
# ---------------------------------------------------------------------------------------------


def _load_suite():
    spec = importlib.util.spec_from_file_location("diagnose_suite",
                                                  os.path.join(ROOT, "benchmarks", "diagnose_suite.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("diagnose_suite", mod)
    spec.loader.exec_module(mod)
    return mod


def _diagnose_tclab(backend, tmp_path):
    S = _load_suite()
    case = next(c for c in S.CASES if c.name == "tclab/thermal_mass")
    net, train, val = S.make_data(case, 0.01, 0, True, str(tmp_path))
    out = tmp_path / "extended.thn"
    d = tnn_dsl.diagnose(net, train, val, backend=backend, top=3, max_rounds=2, output=str(out))
    return S, case, d, out


def _check_tclab(S, case, d, out):
    r = S.score(case, d, 0.01)
    assert r["first_answer"] == "thermal_mass:h1--amb:", d.summary()
    assert r["accepted"] and r["ratio"] >= 2, d.summary()
    f = d.accepted[0]
    assert f.kind == "thermal_mass" and "m_h1_amb" in f.clause and "missing thermal mass between h1 and amb" in f.words
    text = out.read_text(encoding="utf-8")
    assert "\nnode m_h1_amb " in text and text.startswith("# tclab_board (") and "missing thermal mass" in text
    reloaded = tnn_dsl.loads(text, str(out))
    cm = reloaded.param("C_m_h1_amb").value
    assert 1.0 < cm < 9.0  # the planted 3 J/K


def test_diagnose_names_the_missing_thermal_mass_first(tmp_path):
    _check_tclab(*_diagnose_tclab("jax", tmp_path))


@pytest.mark.slow
def test_diagnose_names_the_missing_thermal_mass_first_torch(tmp_path):
    _check_tclab(*_diagnose_tclab("torch", tmp_path))
