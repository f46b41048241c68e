"""Analytic checks of the compiled model on both backends (issue 3 acceptance)."""

from __future__ import annotations

import math

import nets
import numpy as np
import pytest

import tnn_dsl
from tnn_dsl import TnnError
from tnn_dsl.compiler.physics import STEFAN_BOLTZMANN

BACKENDS = ["jax", "torch"]


def np_(model, x):
    return np.asarray(model.xp.to_numpy(x), dtype=float)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("integrator,tol", [("rk4", 1e-9), ("expeuler", 1e-11)])
def test_one_node_step_response(backend, integrator, tol):
    R, C, Ta, Q = 2.0, 50.0, 300.0, 5.0
    m = tnn_dsl.compile(nets.one_node_rc(R, C, Ta, Q=True), backend)
    p = m.init_params()
    N, dt = 400, 1.0
    u = np.tile([Ta, Q], (N, 1))
    states, y = m.rollout(p, np.array([Ta]), u, dt, integrator=integrator)
    t = np.arange(N) * dt
    exact = Ta + Q * R * (1.0 - np.exp(-t / (R * C)))
    assert np.max(np.abs(np_(m, states)[:, 0] - exact)) < tol * Q * R
    np.testing.assert_allclose(np_(m, y)[:, 0], np_(m, states)[:, 0], rtol=0, atol=0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_one_node_euler_is_thesis_eq_4_7(backend):
    R, C, Ta = 2.0, 50.0, 300.0
    m = tnn_dsl.compile(nets.one_node_rc(R, C, Ta), backend)
    N, dt = 50, 3.0
    states, _ = m.rollout(m.init_params(), np.array([310.0]), np.full((N, 1), Ta), dt, integrator="euler")
    k = np.arange(N)
    exact = Ta + 10.0 * (1.0 - dt / (R * C)) ** k  # T_{k+1} = T_k + Δt·f(T_k)
    np.testing.assert_allclose(np_(m, states)[:, 0], exact, rtol=1e-13)


def _two_node_solve_R(R, Ta=300.0, P=10.0):
    G = np.array([[-1.0 / R - 0.8, 0.8], [0.8, -0.8 - 0.25]])
    return np.linalg.solve(G, -np.array([Ta / R + P, 0.25 * 290.0]))


def _two_node_linear_solve(Ta, P):
    # C dT/dt = G T + b; nodes n1, n2; links n1-amb R=2, n1-n2 G=0.8, n2-wall R=4 (wall 290 K)
    G = np.array([[-0.5 - 0.8, 0.8], [0.8, -0.8 - 0.25]])
    b = np.array([0.5 * Ta + P, 0.25 * 290.0])
    return np.linalg.solve(G, -b)


@pytest.mark.parametrize("backend", BACKENDS)
def test_two_node_steady_state_is_the_linear_solve(backend):
    m = tnn_dsl.compile(nets.two_node(), backend)
    p = m.init_params()
    u = np.array([[300.0, 10.0], [280.0, 0.0], [295.0, 42.0]])
    Ts = np_(m, m.steady_state(p, u))
    for k in range(3):
        np.testing.assert_allclose(Ts[k], _two_node_linear_solve(*u[k]), rtol=1e-13)
    # and the rollout converges there; the sensor adds its offset
    states, y = m.rollout(p, np.array([300.0, 300.0]), np.tile(u[0], (20000, 1)), 5.0)
    np.testing.assert_allclose(np_(m, states)[-1], Ts[0], rtol=1e-10)
    np.testing.assert_allclose(np_(m, y)[-1, 0], Ts[0, 1] + 0.25, rtol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_steady_state_gradient_is_the_implicit_derivative(backend):
    m = tnn_dsl.compile(nets.two_node(), backend)
    p = m.init_params()
    u = np.array([300.0, 10.0])

    def T2(R):
        q = dict(p)
        q["R_n1_amb"] = m.xp.asarray(R)
        return m.steady_state(q, u)[1]

    R0, h = 2.0, 1e-5
    fd = (float(np_(m, T2(R0 + h))) - float(np_(m, T2(R0 - h)))) / (2 * h)
    # analytic: dT2/dR for the linear two-node network (T2 falls as the path to the warm ambient weakens)
    exact = (_two_node_linear_solve(300.0, 10.0)[1] - _two_node_solve_R(R0 + h)[1]) / -h
    assert fd == pytest.approx(exact, rel=1e-4) and abs(fd) > 0.1
    if backend == "jax":
        import jax

        g = float(jax.grad(lambda r: T2(r))(R0))
    else:
        import torch

        r = torch.tensor(R0, dtype=torch.float64, requires_grad=True)
        T2(r).backward()
        g = float(r.grad)
    assert abs(g - fd) < 1e-7 * max(1.0, abs(fd))


@pytest.mark.parametrize("backend", BACKENDS)
def test_adiabatic_network_conserves_energy(backend):
    m = tnn_dsl.compile(nets.adiabatic(), backend)
    p = m.init_params()
    C = np.array([10.0, 25.0, 40.0])
    T0 = np.array([350.0, 300.0, 250.0])
    for integrator in ("euler", "rk4"):
        states, _ = m.rollout(p, T0, np.zeros((3000, 0)), 0.2, integrator=integrator)
        E = np_(m, states) @ C
        assert np.max(np.abs(E - E[0])) < 1e-12 * abs(E[0]), integrator
        # and it relaxes to the capacity-weighted mean temperature
        np.testing.assert_allclose(np_(m, states)[-1], E[0] / C.sum(), rtol=1e-6)
    # expeuler scales each node's step by its own φ₁ factor: stable, but energy is conserved only to O(Δt)
    states, _ = m.rollout(p, T0, np.zeros((500, 0)), 0.2, integrator="expeuler")
    E = np_(m, states) @ C
    assert np.max(np.abs(E - E[0])) < 2e-3 * abs(E[0])
    with pytest.raises(TnnError, match="no steady state"):
        m.steady_state(p, np.zeros(0))


@pytest.mark.parametrize("backend", BACKENDS)
def test_peltier_and_fluid_flows_by_hand(backend):
    m = tnn_dsl.compile(nets.peltier_fluid(), backend)
    p = m.init_params()
    T = np.array([310.0, 285.0])  # h, c
    u = np.array([2.5, 298.15])  # I, Tf
    fl = {k: float(np_(m, v)) for k, v in m.heat_flows(p, T, u).items()}
    S, Rel, I = 0.05, 2.0, 2.5
    q_hot = S * 310.0 * I + 0.5 * Rel * I**2
    q_cold = -S * 285.0 * I + 0.5 * Rel * I**2
    a = math.exp(-5.0 / (0.002 * 4186.0))
    q_f = 0.002 * 4186.0 * (1 - a) * (298.15 - 285.0)
    assert fl["pe.Q_hot"] == pytest.approx(q_hot, rel=1e-14)
    assert fl["pe.Q_cold"] == pytest.approx(q_cold, rel=1e-14)
    assert fl["pe.Q_internal"] == pytest.approx((310.0 - 285.0) / 1.5, rel=1e-14)
    assert fl["f1.Q"] == pytest.approx(q_f, rel=1e-13)
    assert fl["R_h_amb.Q"] == pytest.approx((295.0 - 310.0) / 0.5, rel=1e-14)
    dT = np_(m, m.rhs(p, T, u))
    np.testing.assert_allclose(dT[0], (q_hot - 25.0 / 1.5 + (295.0 - 310.0) / 0.5) / 40.0, rtol=1e-13)
    np.testing.assert_allclose(dT[1], (q_cold + 25.0 / 1.5 + q_f) / 40.0, rtol=1e-13)


def _balance_from_flows(m, p, T, u):
    """Σ flows into each node / C, from heat_flows: must equal rhs (same physics, other assembly)."""
    net = m.network
    fl = {k: np_(m, v) for k, v in m.heat_flows(p, T, u).items()}
    idx = {n: i for i, n in enumerate(m.state_names)}
    q = np.zeros(np.shape(T)[:-1] + (len(net.nodes),))

    def add(node, v):
        if node in idx and idx[node] < len(net.nodes):
            q[..., idx[node]] += v

    for lk in net.links:
        add(lk.a, fl[f"{lk.name}.Q"])
        add(lk.b, -fl[f"{lk.name}.Q"])
    for r in net.radiations:
        add(r.a, fl[f"{r.name}.Q"])
        add(r.b, -fl[f"{r.name}.Q"])
    for pe in net.peltiers:
        add(pe.hot, fl[f"{pe.name}.Q_hot"] - fl.get(f"{pe.name}.Q_internal", 0.0))
        add(pe.cold, fl[f"{pe.name}.Q_cold"] + fl.get(f"{pe.name}.Q_internal", 0.0))
    for f in net.fluids:
        add(f.node, fl[f"{f.name}.Q"])
    for s in net.sources:
        add(s.node, fl[f"{s.name}.Q"])
    for k, v in fl.items():
        if k.startswith("Q["):
            add(k[2:-1], v)
    pv = m.to_numpy(p)
    C = np.array([float(pv[nd.capacitance]) for nd in net.nodes])
    return q / C


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("learn", [None, "mlp", "mlp_peltier"])
def test_rhs_equals_sum_of_heat_flows(backend, learn):
    m = tnn_dsl.compile(nets.case_study(learn, extra=True), backend)
    p = m.init_params(3)
    rng = np.random.default_rng(0)
    p = m.from_numpy({k: v + (0.2 * rng.standard_normal(v.shape) if k.endswith(("W2", ".W", ".b2")) else 0.0)
                      for k, v in m.to_numpy(p).items()})
    T = 290.0 + 20.0 * rng.random((4, len(m.state_names)))
    u = np.column_stack([3 * rng.random(4), rng.random(4), np.full(4, 295.0), np.full(4, 298.0), np.full(4, 298.0)])
    dT = np_(m, m.rhs(p, T, u))
    n = len(m.network.nodes)
    np.testing.assert_allclose(dT[:, :n], _balance_from_flows(m, p, T, u), rtol=1e-10, atol=1e-12)
    # lag state: (T_node − T_s)/τ
    np.testing.assert_allclose(dT[:, n], (T[:, 5] - T[:, n]) / 5.0, rtol=1e-13)


@pytest.mark.parametrize("backend", BACKENDS)
def test_radiation_and_table_conductance(backend):
    m = tnn_dsl.compile(nets.case_study(None, extra=True), backend)
    p = m.init_params()
    T = np.full(len(m.state_names), 300.0)
    T[2] = 330.0  # hs
    T[6] = 273.15 + 10.0  # base
    T[5] = 273.15 + 30.0  # hx2 → mean(base, hx2) = 20 °C → G = 2.0 + 0.4·20/50
    u = np.array([0.0, 0.0, 280.0, 298.15, 298.15])
    fl = {k: float(np_(m, v)) for k, v in m.heat_flows(p, T, u).items()}
    assert fl["rad_hs_amb.Q"] == pytest.approx(STEFAN_BOLTZMANN * 0.9 * 0.02 * (280.0**4 - 330.0**4), rel=1e-13)
    assert fl["G_tab.Q"] == pytest.approx((2.0 + 0.4 * 20.0 / 50.0) * (T[5] - T[6]), rel=1e-13)


@pytest.mark.parametrize("backend", BACKENDS)
def test_scale_keys(backend):
    m = tnn_dsl.compile(nets.peltier_fluid(), backend)
    p = m.init_params()
    T, u = np.array([310.0, 285.0]), np.array([2.0, 298.15])
    base = {k: float(np_(m, v)) for k, v in m.heat_flows(p, T, u).items()}
    q = dict(p)
    q["scale:R_h_amb"] = 2.0  # the resistance doubles → flow halves
    q["scale:pe.Q_hot"] = 1.5
    q["scale:f1.UA"] = 0.0 + 1.0
    fl = {k: float(np_(m, v)) for k, v in m.heat_flows(q, T, u).items()}
    assert fl["R_h_amb.Q"] == pytest.approx(base["R_h_amb.Q"] / 2.0, rel=1e-14)
    assert fl["pe.Q_hot"] == pytest.approx(base["pe.Q_hot"] * 1.5, rel=1e-14)
    assert fl["pe.Q_cold"] == pytest.approx(base["pe.Q_cold"], rel=1e-14)
    dT = np_(m, m.rhs(q, T, u))
    np.testing.assert_allclose(
        dT[0], (1.5 * base["pe.Q_hot"] - base["pe.Q_internal"] + base["R_h_amb.Q"] / 2.0) / 40.0, rtol=1e-13)
    with pytest.raises(TnnError, match="unknown scale key"):
        m.rhs({**p, "scale:nope": 1.0}, T, u)
    missing = dict(p)
    del missing["C_h"]
    with pytest.raises(TnnError, match="lacks 'C_h'"):
        m.rhs(missing, T, u)


@pytest.mark.parametrize("backend", BACKENDS)
def test_sensor_lag_and_offset(backend):
    m = tnn_dsl.compile(nets.case_study(None, extra=True), backend)
    assert m.state_names[-1] == "T_out.lag"
    assert m.output_names == ("T_out", "T_hs")
    p = m.init_params()
    T = np.linspace(290, 300, len(m.state_names))
    y = np_(m, m.outputs(p, T, np.zeros(5)))
    assert y[0] == pytest.approx(T[-1] + 0.1, rel=1e-15)
    assert y[1] == pytest.approx(T[2], rel=1e-15)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_rollout_matches_single(backend):
    m = tnn_dsl.compile(nets.case_study("mlp", extra=True), backend)
    p = m.init_params(1)
    u = np.stack([nets.case_inputs(60, seed=s) for s in (1, 2, 3)])
    T0 = np.full((3, len(m.state_names)), 298.15) + np.arange(3)[:, None]
    S, Y = m.rollout(p, T0, u, 1.0)
    assert tuple(np_(m, S).shape) == (3, 60, len(m.state_names))
    assert tuple(np_(m, Y).shape) == (3, 60, 2)
    for k in range(3):
        s, y = m.rollout(p, T0[k], u[k], 1.0)
        np.testing.assert_allclose(np_(m, S)[k], np_(m, s), rtol=1e-14)
        np.testing.assert_allclose(np_(m, Y)[k], np_(m, y), rtol=1e-14)
    np.testing.assert_array_equal(np_(m, S)[:, 0], T0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_param_specs_and_numpy_round_trip(backend):
    m = tnn_dsl.compile(nets.case_study("mlp"), backend)
    specs = m.param_specs
    assert specs["C_ph"].kind == "physical" and specs["C_ph"].positive and not specs["C_ph"].trainable
    assert specs["pe.seebeck"].trainable
    assert specs["R_hp1"].kind == "physical" and not specs["R_hp1"].trainable  # learned target
    assert specs["f1_hp.W0"].shape == (4, 8) and specs["f1_hp.W2"].shape == (8, 3)
    assert specs["f1_hp.x_mean"].kind == "stat" and not specs["f1_hp.x_mean"].trainable
    p = m.init_params(0)
    assert set(p) == set(specs)
    back = m.from_numpy(m.to_numpy(p))
    for k in p:
        np.testing.assert_array_equal(np_(m, back[k]), np_(m, p[k]))
    assert m.to_numpy(p)["f1_hp.x_mean"].tolist() == [298.15, 298.15, 298.15, 0.0]
    with pytest.raises(TnnError, match="shape"):
        m.from_numpy({"f1_hp.W0": np.zeros((3, 8))})


@pytest.mark.parametrize("backend", BACKENDS)
def test_float32(backend):
    m64 = tnn_dsl.compile(nets.case_study("mlp"), backend)
    m32 = tnn_dsl.compile(nets.case_study("mlp"), backend, dtype="float32")
    u = nets.case_inputs(300)
    T0 = np.full(7, 298.15)
    s64, _ = m64.rollout(m64.init_params(0), T0, u, 1.0)
    s32, _ = m32.rollout(m32.init_params(0), T0, u, 1.0)
    assert np_(m32, s32).dtype == np.float64  # np_ converts; check the backend dtype directly
    assert "32" in str(s32.dtype)
    np.testing.assert_allclose(np_(m32, s32), np_(m64, s64), atol=2e-3)


def test_bad_arguments():
    m = tnn_dsl.compile(nets.one_node_rc(), "jax")
    p = m.init_params()
    with pytest.raises(TnnError, match="unknown integrator"):
        m.rollout(p, np.array([300.0]), np.full((3, 1), 300.0), 1.0, integrator="heun")
    with pytest.raises(TnnError, match="T0 must have shape"):
        m.rollout(p, np.array([300.0, 1.0]), np.full((3, 1), 300.0), 1.0)
    with pytest.raises(TnnError, match="inputs must have shape"):
        m.rollout(p, np.array([300.0]), np.full((3, 2), 300.0), 1.0)
    with pytest.raises(TnnError, match="unknown backend"):
        tnn_dsl.compile(nets.one_node_rc(), "tensorflow")


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_params_passed_in_override_the_file_values_and_have_gradients(backend):
    """Regression: the value of a constant parameter passed in ``params`` must be the one used (the
    trainer found it once silently replaced by the file's literal, which zeroed every gradient)."""
    import tnn_dsl

    net = tnn_dsl.loads(
        "network rc\nunits temperature = K\nparam Ta = 300 K\nboundary amb = Ta\n"
        "node a C = 100 J/K free\nR a -- amb = 2 K/W free\nsource a = 10 W\nsensor Ta_s = a column \"T\"\n")
    m = tnn_dsl.compile(net, backend=backend)
    p0 = m.to_numpy(m.init_params())
    T_ss = m.to_numpy({"x": m.steady_state(m.init_params(), m.from_numpy({"u": np.zeros(0)})["u"])})["x"]
    np.testing.assert_allclose(T_ss, [320.0], rtol=1e-12)
    p1 = dict(p0, R_a_amb=np.asarray(4.0))
    T_ss1 = m.to_numpy({"x": m.steady_state(m.from_numpy(p1), m.from_numpy({"u": np.zeros(0)})["u"])})["x"]
    np.testing.assert_allclose(T_ss1, [340.0], rtol=1e-12)
    # gradient of the final temperature of a 100 s rollout w.r.t. C and R is non-zero
    if backend == "jax":
        import jax
        import jax.numpy as jnp

        def final(p):
            _, y = m.rollout(p, jnp.array([300.0]), jnp.zeros((100, 0)), 1.0)
            return y[-1, 0]

        g = jax.grad(final)(m.init_params())
        assert float(g["C_a"]) != 0.0 and float(g["R_a_amb"]) != 0.0
    else:
        import torch

        p = {k: v.clone().requires_grad_(True) for k, v in m.init_params().items()}
        _, y = m.rollout(p, torch.tensor([300.0], dtype=torch.float64), torch.zeros((100, 0), dtype=torch.float64), 1.0)
        y[-1, 0].backward()
        assert float(p["C_a"].grad) != 0.0 and float(p["R_a_amb"].grad) != 0.0
