"""Candidate families of the model doctor beyond "linear in one variable", and which candidates may be fitted.

* Curved shapes (:meth:`tnn_dsl.doctor.candidates._Extension.curved_shapes`): a square ``v²`` or a product ``v·w``
  in the same learned function as the linear candidates (a ``poly`` of degree 2, exactly null at zero), scored only
  once a linear dependence of the same target on one of its variables is accepted, written ``as poly(…; degree =
  2)`` and read back as a law in physical units.
* A heat capacity depends on its node's temperature, never on a command or a data column; a heater command changes
  its own source's heat, never a conductance.
* A learned function of several targets (M1's ``learn R_hp1, R_hp2, R_hpa as const``) may depend on a variable as a
  whole: one candidate, one column per target, written ``learn R_hp1, R_hp2, R_hpa as linear(u1)``.
* On the real TCLab board (Kuntz & Rawlings' PRBS run, MIT; the closed-loop set-point run is validation-only and is
  only the held-out judge here), the doctor accepts both sensor lags, every accepted cause is physical, and the
  held-out error falls at least 1.6-fold (issue 17's acceptance; see ``examples/diagnose_real_data.py``).
"""

from __future__ import annotations

import os
from types import SimpleNamespace

import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler import compile as compile_network
from tnn_dsl.doctor.candidates import build_extended
from tnn_dsl.doctor.extension import extend_network
from tnn_dsl.doctor.session import _Session
from tnn_dsl.doctor.words import _words
from tnn_dsl.lang import print_thn
from tnn_dsl.studies.planted import plant

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
TCLAB = os.path.join(ROOT, "networks", "tclab", "tclab.thn")
M1 = os.path.join(ROOT, "networks", "peltier_heatpipe", "m1.thn")
DATA = os.path.join(os.path.dirname(ROOT), "shared", "data")
PRBS = os.path.join(DATA, "tclab_kuntz_rawlings_prbs_openloop.csv")
SETPOINT = os.path.join(DATA, "tclab_kuntz_rawlings_closedloop_setpoint.csv")  # validation-only
BOUNDS = {"Q1": (0.0, 1.0), "Q2": (0.0, 1.0)}


def _cand(ext, key):
    return next(c for c in ext.candidates if c.key == key)


def test_curved_candidates_sit_in_the_linear_function_and_wait_for_their_linear_parent():
    net = tnn_dsl.load(TCLAB)
    ext = build_extended(net, ["Q1", "Q2"])
    quad = _cand(ext, "heat_load:Q[h2]:Q1²")
    prod = _cand(ext, "heat_load:Q[h2]:Q1·T(h2)")
    lin = _cand(ext, "heat_load:Q[h2]:Q1")
    assert quad.fn == prod.fn == lin.fn and quad.k == prod.k == 1
    fn = next(f for f in ext.network.learned if f.name == quad.fn)
    assert fn.kind == "poly" and fn.degree == 2
    assert quad.element["parents"] == [lin.key]
    assert set(prod.element["parents"]) == {lin.key, "heat_load:Q[h2]:T(h2)"}
    # the session's gate: no curved candidate before its linear parent is accepted, then its own ones only
    ns = SimpleNamespace(accepted=[], ext=ext, with_struct=False, net_x=net, kinds=None)
    before = {c.key for c in _Session.candidates_now(ns)}
    assert lin.key in before and quad.key not in before and prod.key not in before
    ns.accepted = [lin]
    after = {c.key for c in _Session.candidates_now(ns)}
    assert quad.key in after and prod.key in after and lin.key not in after
    assert "heat_load:Q[h1]:Q1²" not in after


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_the_poly_extension_is_exactly_null_and_a_planted_square_is_not(backend):
    net = tnn_dsl.load(TCLAB)
    null = plant(net, BOUNDS, None, n_train=200, n_val=50, backend=backend)
    sq = plant(net, BOUNDS, "heat_load", "Q[h2]", "Q1²", 0.3, n_train=200, n_val=50, backend=backend)
    # the null data come from the extended network at zero: the plain network gives the same readings
    model = compile_network(net, backend=backend, dtype="float64")
    p = model.init_params(0)
    u = np.asarray(null.train[0].inputs)
    T0 = model.steady_state(p, u[0])
    _, y = model.rollout(p, T0, u, 1.0)
    np.testing.assert_allclose(np.asarray(model.xp.to_numpy(y)), null.train[0].outputs, atol=1e-9)
    # a square in Q1 warms h2 (read by T2) and leaves T1 nearly alone
    d = sq.train[0].outputs - null.train[0].outputs
    assert np.abs(d[:, 1]).max() > 0.05 and np.abs(d[:, 1]).max() > 3 * np.abs(d[:, 0]).max()


def test_a_curved_finding_reads_as_a_law_and_is_written_as_poly():
    net = tnn_dsl.load(TCLAB)
    ext = build_extended(net, ["Q1", "Q2"])
    lin, quad = _cand(ext, "heat_load:Q[h2]:Q1"), _cand(ext, "heat_load:Q[h2]:Q1²")
    model = compile_network(ext.network, backend="jax", dtype="float64")
    params = {k: np.array(v, dtype=float) for k, v in model.to_numpy(model.init_params(0)).items()}
    fn = quad.fn
    params[f"{fn}.x_mean"][:] = 0.5
    params[f"{fn}.x_scale"][:] = 0.5
    j = quad.element["output"]
    params[f"{fn}.y_scale"][j] = 1.0
    for col, v in ((lin.columns[0], 0.2), (lin.columns[1], 0.1), (quad.columns[0], 0.05)):
        params[col.key].reshape(-1)[col.index] = v
    words = _words(quad, params, ext, None, model)
    # z = 0.1 + 0.2·(Q1 − 0.5)/0.5 + 0.05·((Q1 − 0.5)/0.5)²: 0.4 W per unit of Q1, 0.2 W per unit²
    assert "Q[h2] ≈ 0.1 + 0.4·(Q1 − 0.5) + 0.2·(Q1 − 0.5)² W" in words, words
    written = extend_network(net, [lin, quad], params)
    text = print_thn(written)
    assert "as poly(Q1; degree = 2)" in text, text
    back = tnn_dsl.loads(text, filename="extended.thn")
    assert any(f.kind == "poly" and f.degree == 2 for f in back.learned)


def test_a_heat_capacity_depends_on_its_temperature_never_on_a_command():
    ext = build_extended(tnn_dsl.load(TCLAB), ["Q1", "Q2"])
    on_c = [c for c in ext.candidates if c.kind == "param_dependence" and c.target in ("C_h1", "C_h2")]
    assert on_c and all(d.startswith("T(") for c in on_c for d in c.depends_on), [c.key for c in on_c]


def test_a_heater_command_changes_its_source_never_a_conductance():
    """Q1 and Q2 only set the heaters' power: a conductance may depend on the temperatures they cause, never on
    the commands themselves; the sources' heat (and their gains) may depend on any command."""
    keys = {c.key for c in build_extended(tnn_dsl.load(TCLAB), ["Q1", "Q2"]).candidates}
    assert not {k for k in keys if k.startswith(("param_dependence:U1:Q", "param_dependence:U12:Q"))}, sorted(keys)
    assert {"param_dependence:U1:T(h1)", "param_dependence:Q_src_h1:Q2", "param_dependence:a1:Q1"} <= keys, sorted(keys)


@pytest.mark.skipif(not (os.path.isfile(PRBS) and os.path.isfile(SETPOINT)), reason="shared TCLab data not present")
@pytest.mark.parametrize("backend,kinds", [
    ("jax", ("sensor_lag", "source_mass")),
    pytest.param("jax", None, marks=pytest.mark.slow), pytest.param("torch", None, marks=pytest.mark.slow)])
def test_real_tclab_sensor_lags_pay_on_the_set_point_run(backend, kinds):
    """With every kind of candidate (slow): both lags, then U12 rising with T(h1), ÷2.01 (README). In CI only the
    lags and their equally fast rival, a heat capacity behind a heater's source, are offered: both lags are taken
    (÷1.59, as much as a hand-built four-state model with sensor lags) and the source's capacity, which would reach
    thousands of degrees, is not."""
    d = tnn_dsl.diagnose(TCLAB, [PRBS], [SETPOINT], backend=backend, mlp_check=False,
                         **({"kinds": kinds} if kinds else {}))
    kinds = [(f.kind, f.target) for f in d.accepted]
    assert ("sensor_lag", "T1") in kinds and ("sensor_lag", "T2") in kinds, d.summary()
    assert d.baseline["val_mae"] / d.extended["val_mae"] >= (1.6 if kinds is None else 1.55), d.summary()
    # every accepted cause is physical (no node far outside the data, no value beyond the network's scales)
    assert all(f.evidence["plausibility"] == "ok" for f in d.accepted), d.summary()
    # the diagnosed model (two lag states, the doctor's values) free-runs the measured held-out run to the error the
    # report gives: what `tnnc diagnose --model DIR` writes and `tnnc evaluate` reads
    assert d.model.evaluate([SETPOINT])["mae"] == pytest.approx(d.extended["val_mae"], rel=1e-9)


def test_a_caution_never_names_a_twin_the_held_out_run_separates():
    from tnn_dsl.doctor.results import Diagnosis, Finding

    twins = [{"candidate": "R_hp2 depends on u1", "key": "a", "cos": 0.99},
             {"candidate": "f2.mdot depends on u1", "key": "b", "cos": 0.98, "val_mae": 0.06, "separated": True},
             {"candidate": "R_pc_hx1 depends on u1", "key": "c", "cos": 0.97, "val_mae": float("nan"),
              "separated": True}]
    f = Finding(rank=1, kind="param_dependence", target="R_hp1", depends_on=["u1"], clause="", val_mae_after=0.012,
                val_max_after=0.05, accepted=True, words="R_hp1 depends on u1",
                evidence={"val_mae_before": 0.17, "p_value": 1e-8, "n_eff": 30, "indistinguishable_from": twins})
    row = Diagnosis.finding_rows(SimpleNamespace(findings=[f]))[0]
    assert row["caution"] == "R_hp2 depends on u1 (|cos| = 0.990)"
    assert "f2.mdot depends on u1 (held-out MAE 0.06 K against 0.012 K)" in row["separated"]
    assert "R_pc_hx1 depends on u1 (its fit diverged)" in row["separated"]


def test_a_learned_function_of_several_targets_may_depend_on_a_variable_as_a_whole():
    net = tnn_dsl.load(M1)
    ext = build_extended(net, ["I", "u1"])
    whole = _cand(ext, "param_dependence:R_hp1, R_hp2, R_hpa:u1")
    parts = [_cand(ext, f"param_dependence:{t}:u1") for t in ("R_hp1", "R_hp2", "R_hpa")]
    # one column per target, the very columns of the per-target candidates, in the user's own function
    assert whole.k == 3 and [m.key for m in whole.members] == [p.key for p in parts]
    assert [c.key for c in whole.columns] == [p.columns[0].key for p in parts]
    assert {c.index for c in whole.columns} == {p.columns[0].index for p in parts}
    assert whole.fn == "fn_R_hp1" and whole.element["learned"] == "fn_R_hp1"
    # only variables every target may depend on: T(hx1) is R_hp1's alone
    assert not any(c.element.get("members") and c.depends_on == ["T(hx1)"] for c in ext.candidates)
    # the small network of the proper fit holds it alone, and the extension writes the user's function as linear
    small = build_extended(net, ["I", "u1"], only={whole.key})
    assert [c.key for c in small.candidates] == [whole.key]
    model = compile_network(small.network, backend="jax", dtype="float64")
    params = {k: np.array(v, dtype=float) for k, v in model.to_numpy(model.init_params(0)).items()}
    sc = _cand(small, whole.key)
    params[f"{sc.fn}.W"].reshape(-1)[[c.index for c in sc.columns]] = (0.3, 0.2, 0.1)
    text = print_thn(extend_network(net, [sc], params))
    assert "learn R_hp1, R_hp2, R_hpa as linear(u1)" in text and "as const" not in text, text
    words = _words(sc, params, small, None, model)
    assert words.startswith("R_hp1, R_hp2, R_hpa (one learned function) depend together on u1: R_hp1"), words
    assert all(f"{t} ≈" in words for t in ("R_hp1", "R_hp2", "R_hpa")), words
