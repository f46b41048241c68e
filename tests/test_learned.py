"""Learned functions: shapes, initial output zero, positivity, tables, and the untrained = nominal rule."""

from __future__ import annotations

import math

import nets
import numpy as np
import pytest

import tnn_dsl
from tnn_dsl.compiler import learned as _learned
from tnn_dsl.compiler.backends import get_xp
from tnn_dsl.ir.network import LearnFunction, LearnTarget

BACKENDS = ["jax", "torch"]


def _fn(kind, n_out=2, **kw):
    return LearnFunction(name="f", kind=kind, targets=[LearnTarget(kind="param", name=f"p{i}") for i in range(n_out)],
                         **kw)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("kind,kw,n_in", [
    ("const", {}, 0), ("linear", {}, 3), ("poly", {"degree": 3}, 2),
    ("mlp", {"hidden": [8, 8], "activation": "sigmoid"}, 4), ("mlp", {"hidden": [5], "activation": "silu"}, 2),
    ("table", {"knots": [280.0, 300.0, 320.0]}, 1),
])
def test_untrained_output_is_zero_and_shapes(backend, kind, kw, n_in):
    xp = get_xp(backend)
    fn = _fn(kind, **kw)
    arrays = _learned.init_arrays(fn, n_in, 2, np.random.default_rng(0), x_mean=290.0, x_scale=10.0)
    for name, (shape, _) in _learned.array_shapes(fn, n_in, 2).items():
        assert arrays[name].shape == shape
    x = xp.asarray(np.random.default_rng(1).uniform(270, 330, (5, 7, n_in)))
    z = np.asarray(xp.to_numpy(_learned.apply(xp, fn, {k: xp.asarray(v) for k, v in arrays.items()}, x)))
    assert np.all(z == 0.0) and z.shape[-1] == 2


def test_poly_monomials():
    idx = _learned.monomial_index(3, 2)
    assert len(idx) == math.comb(3 + 2, 2) - 1  # 1…2-degree monomials of 3 variables
    assert len({tuple(sorted(r)) for r in idx.tolist()}) == len(idx)


@pytest.mark.parametrize("backend", BACKENDS)
def test_poly_and_mlp_values(backend):
    xp = get_xp(backend)
    rng = np.random.default_rng(0)
    fn = _fn("poly", n_out=1, degree=2)
    arrays = _learned.init_arrays(fn, 2, 1, rng)
    arrays["W"] = rng.standard_normal(arrays["W"].shape)
    arrays["b"] = np.array([0.5])
    x = rng.standard_normal((6, 2))
    z = np.asarray(xp.to_numpy(_learned.apply(xp, fn, {k: xp.asarray(v) for k, v in arrays.items()}, xp.asarray(x))))
    idx = _learned.monomial_index(2, 2)
    X = np.column_stack([np.ones(6), x])
    feats = X[:, idx[:, 0]] * X[:, idx[:, 1]]
    np.testing.assert_allclose(z, feats @ arrays["W"] + 0.5, rtol=1e-14)
    fn = _fn("mlp", n_out=2, hidden=[3], activation="tanh")
    arrays = {k: rng.standard_normal(v.shape) for k, v in _learned.init_arrays(fn, 2, 2, rng).items()}
    arrays["x_scale"] = np.abs(arrays["x_scale"]) + 0.5
    z = np.asarray(xp.to_numpy(_learned.apply(xp, fn, {k: xp.asarray(v) for k, v in arrays.items()}, xp.asarray(x))))
    xn = (x - arrays["x_mean"]) / arrays["x_scale"]
    np.testing.assert_allclose(z, np.tanh(xn @ arrays["W0"] + arrays["b0"]) @ arrays["W1"] + arrays["b1"], rtol=1e-13)


@pytest.mark.parametrize("backend", BACKENDS)
def test_table_interpolates_and_holds_beyond_the_ends(backend):
    xp = get_xp(backend)
    knots = [0.0, 1.0, 3.0]
    values = np.array([[1.0, 0.0], [2.0, 10.0], [0.0, 4.0]])
    x = np.array([-5.0, 0.0, 0.5, 1.0, 2.0, 3.0, 9.0])
    z = np.asarray(xp.to_numpy(_learned.table_apply(xp, knots, xp.asarray(values), xp.asarray(x))))
    for j in range(2):
        np.testing.assert_allclose(z[:, j], np.interp(x, knots, values[:, j]), rtol=1e-15)
    y = np.asarray(xp.to_numpy(xp.interp(xp.asarray(x), knots, values[:, 1])))
    np.testing.assert_allclose(y, np.interp(x, knots, values[:, 1]), rtol=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_target_value(backend):
    xp = get_xp(backend)
    z = xp.asarray(np.linspace(-30, 30, 61))
    pos = np.asarray(xp.to_numpy(_learned.target_value(xp, z, 0.2, True, 5.0)))
    assert np.all(pos > 0)
    assert pos[30] == 0.2  # exactly the nominal at z = 0
    assert pos[-1] == pytest.approx(0.2 * 4 * 31 / math.log1p(math.exp(4)), rel=1e-12)  # linear for large z
    lin = np.asarray(xp.to_numpy(_learned.target_value(xp, z, 3.0, False, 2.0)))
    np.testing.assert_allclose(lin, 3.0 + 2.0 * np.linspace(-30, 30, 61), rtol=1e-15)
    rep = np.asarray(xp.to_numpy(_learned.target_value(xp, z, 3.0, False, 2.0, replace=True)))
    np.testing.assert_allclose(rep, 2.0 * np.linspace(-30, 30, 61), rtol=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("learn", ["const", "linear", "mlp", "mlp_peltier"])
def test_untrained_learned_model_reproduces_the_nominal_model(backend, learn):
    nominal = tnn_dsl.compile(nets.case_study(None), backend)
    learned = tnn_dsl.compile(nets.case_study(learn), backend)
    u = nets.case_inputs(400, seed=3)
    T0 = np.full(7, 298.15)
    s0, y0 = nominal.rollout(nominal.init_params(), T0, u, 1.0)
    s1, y1 = learned.rollout(learned.init_params(7), T0, u, 1.0)
    np.testing.assert_allclose(np.asarray(learned.xp.to_numpy(s1)), np.asarray(nominal.xp.to_numpy(s0)),
                               rtol=1e-14, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_learned_heat_load_and_replaced_flow(backend):
    # a poly heat load on hp, untrained: no heat; with weights: exactly y_scale·z into hp
    m = tnn_dsl.compile(nets.case_study(None, extra=True), backend)
    p = m.to_numpy(m.init_params())
    T = np.full(8, 300.0)
    u = np.array([1.0, 0.5, 295.0, 298.0, 298.0])
    fl = m.heat_flows(m.from_numpy(p), T, u)
    assert float(np.asarray(m.xp.to_numpy(fl["Q[hp]"]))) == 0.0
    p["f_load.b"] = np.array([1.25])
    p["f_load.y_scale"] = np.array([2.0])
    fl = m.heat_flows(m.from_numpy(p), T, u)
    assert float(np.asarray(m.xp.to_numpy(fl["Q[hp]"]))) == pytest.approx(2.5, rel=1e-15)
    # Peltier flows replaced by a net: the physics is gone, the net's output (here a constant) remains
    net = nets.case_study("mlp_peltier")
    net.learned[0] = net.learned[0].model_copy(update={"replace": True})
    m = tnn_dsl.compile(net, backend)
    p = m.to_numpy(m.init_params())
    p["f_pe.b2"] = np.array([3.0, -1.0])
    fl = m.heat_flows(m.from_numpy(p), np.full(7, 300.0), u)
    assert float(np.asarray(m.xp.to_numpy(fl["pe.Q_hot"]))) == pytest.approx(3.0, rel=1e-15)
    assert float(np.asarray(m.xp.to_numpy(fl["pe.Q_cold"]))) == pytest.approx(-1.0, rel=1e-15)


def test_default_normalisation():
    m = tnn_dsl.compile(nets.case_study("mlp_peltier"), "jax")
    p = m.to_numpy(m.init_params())
    assert p["f_pe.x_mean"].tolist() == [298.15, 298.15, 0.0]
    assert p["f_pe.x_scale"].tolist() == [10.0, 10.0, 1.0]
    m = tnn_dsl.compile(nets.case_study("linear"), "jax")
    assert m.to_numpy(m.init_params())["f1_hp.y_scale"].tolist() == [0.2, 0.2, 10.0]
