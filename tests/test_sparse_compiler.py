"""Sparse constant matrices for large networks (issue 18): the same numbers as the dense form on every
component kind and backend, steady states by Newton–Krylov with exact implicit gradients, no (n, n) array in
a sparse model, and the large-network generators."""

from __future__ import annotations

import os

import nets
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tnn_dsl
from tnn_dsl.compiler.assembly import SPARSE_MIN_STATES
from tnn_dsl.compiler.sparse import Coo, SparseMatrix, as_matrix
from tnn_dsl.studies.large_networks import building_thn, plate_size, plate_thn

BACKENDS = ("jax", "torch")
NETWORKS = os.path.join(os.path.dirname(__file__), "..", "networks")


def _grads(model, p_np, T0, u, w, integrator="rk4"):
    """States, outputs and the gradient of a weighted output sum w.r.t. every parameter (numpy)."""
    N = u.shape[0]
    if model.backend == "jax":
        import jax

        p = model.from_numpy(p_np)

        def loss(p):
            s, y = model.rollout(p, T0, u, 1.0, integrator=integrator)
            return (y * w).sum() / N, (s, y)

        # the states and outputs from the differentiated run itself: one compiled forward pass, not two
        g, (s, y) = jax.grad(loss, has_aux=True)(p)
        return np.asarray(s), np.asarray(y), {k: np.asarray(v) for k, v in g.items()}
    import torch

    p = {k: v.requires_grad_(True) for k, v in model.from_numpy(p_np).items()}
    s, y = model.rollout(p, T0, u, 1.0, integrator=integrator)
    (y * torch.as_tensor(w)).sum().div(N).backward()
    return (s.detach().numpy(), y.detach().numpy(),
            {k: np.zeros(v.shape) if v.grad is None else v.grad.numpy() for k, v in p.items()})


def _assert_same(a, b):
    sa, ya, ga = a
    sb, yb, gb = b
    assert np.max(np.abs(sa - sb)) <= 1e-9
    assert np.max(np.abs(ya - yb)) <= 1e-9
    scale = max(float(np.max(np.abs(g))) for g in ga.values() if g.size)
    for k in ga:
        if ga[k].size:
            err = float(np.max(np.abs(ga[k] - gb[k])))
            assert err <= 1e-6 * max(float(np.max(np.abs(ga[k]))), 1e-8 * scale), k


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("learn,integrator", [("mlp", "rk4"), ("mlp_peltier", "rk4"), ("linear", "expeuler")])
def test_sparse_equals_dense_on_every_component_kind(backend, learn, integrator):
    # the case study with every component kind: Peltier, fluids, radiation, a table conductance, lagged
    # offset sensor, learned resistances / Peltier flows / heat load, derived source
    net = nets.case_study(learn, extra=True)
    dense = tnn_dsl.compile(net, backend, sparse=False)
    sparse = tnn_dsl.compile(net, backend, sparse=True)
    assert not dense.sparse and sparse.sparse
    p_np = nets.random_params(dense, 3)
    u = nets.case_inputs(120, seed=2)
    T0 = np.full(len(dense.state_names), 298.15) + np.linspace(-2, 2, len(dense.state_names))
    w = np.random.default_rng(4).standard_normal((120, len(dense.output_names)))
    _assert_same(_grads(dense, p_np, T0, u, w, integrator), _grads(sparse, p_np, T0, u, w, integrator))


def _shipped(quick):
    files = []
    for root, _, names in os.walk(NETWORKS):
        files += [os.path.join(root, f) for f in names if f.endswith(".thn") and "parts" not in root]
    assert len(files) >= 15
    if quick:  # one of each family in CI; every file in the slow variant
        keep = ("tite.thn", "tclab_lag.thn", "m3.thn", "two_rooms_subnet.thn")
        files = [f for f in files if os.path.basename(f) in keep]
        assert len(files) == len(keep)
    return sorted(files)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("quick", [True, pytest.param(False, marks=pytest.mark.slow)])
def test_shipped_networks_sparse_equals_dense(backend, quick):
    rng = np.random.default_rng(0)
    for f in _shipped(quick):
        net = tnn_dsl.load(f)
        dense = tnn_dsl.compile(net, backend, sparse=False)
        sparse = tnn_dsl.compile(net, backend, sparse=True)
        u = np.asarray([[293.15 if i.is_temperature else v for i, v in zip(net.inputs, row)]
                        for row in rng.uniform(0, 2, (60, len(net.inputs)))]).reshape(60, len(net.inputs))
        T0 = 298.15 + rng.normal(0, 2, len(dense.state_names))
        sd, yd = dense.rollout(dense.init_params(1), T0, u, 1.0)
        ss, ys = sparse.rollout(sparse.init_params(1), T0, u, 1.0)
        assert np.max(np.abs(dense.xp.to_numpy(sd) - sparse.xp.to_numpy(ss))) <= 1e-9, f
        rd, dd = dense.rhs_and_diag(dense.init_params(1), T0, u[0])
        rs, ds = sparse.rhs_and_diag(sparse.init_params(1), T0, u[0])
        assert np.max(np.abs(dense.xp.to_numpy(dd) - sparse.xp.to_numpy(ds))) <= 1e-12, f


@pytest.mark.parametrize("backend", BACKENDS)
def test_sparse_steady_state_and_its_implicit_gradient(backend):
    net = nets.case_study("linear", extra=True)
    dense = tnn_dsl.compile(net, backend, sparse=False)
    sparse = tnn_dsl.compile(net, backend, sparse=True)
    p_np = nets.random_params(dense, 2)
    u = np.array([[2.0, 0.3, 295.15, 298.15, 298.15], [1.0, 0.8, 290.0, 300.0, 298.0]])
    out = []
    for m in (dense, sparse):
        if backend == "jax":
            import jax

            p = m.from_numpy(p_np)
            T = np.asarray(m.steady_state(p, u))
            g = {k: np.asarray(v) for k, v in jax.grad(lambda p: m.steady_state(p, u)[:, 5].sum())(p).items()}
        else:
            p = {k: v.requires_grad_(True) for k, v in m.from_numpy(p_np).items()}
            Tt = m.steady_state(p, u)
            Tt[:, 5].sum().backward()
            T = Tt.detach().numpy()
            g = {k: np.zeros(v.shape) if v.grad is None else v.grad.numpy() for k, v in p.items()}
        assert np.max(np.abs(m.xp.to_numpy(m.rhs(m.from_numpy(p_np), T, u)))) < 1e-10
        out.append((T, g))
    (Td, gd), (Ts, gs) = out
    assert np.max(np.abs(Td - Ts)) <= 1e-9
    scale = max(float(np.max(np.abs(v))) for v in gd.values())
    for k in gd:
        assert np.max(np.abs(gd[k] - gs[k])) <= 1e-6 * max(float(np.max(np.abs(gd[k]))), 1e-8 * scale), k


def _chain(n, T_left=300.0, T_right=310.0):
    lines = ["network chain", "param TL = %g K" % T_left, "param TR = %g K" % T_right,
             "boundary left = TL", "boundary right = TR"]
    lines += [f"node n{i} C = {1.0 + (i % 7)} J/K" for i in range(n)]
    lines += [f"R n{i} -- n{i + 1} = 0.5 K/W" for i in range(n - 1)]
    lines += ["R left -- n0 = 0.25 K/W", f"R n{n - 1} -- right = 0.25 K/W", f"sensor Tm = n{n // 2}"]
    return tnn_dsl.loads("\n".join(lines) + "\n", "chain.thn")


@pytest.mark.parametrize("backend", BACKENDS)
def test_large_chain_steady_state_is_the_analytic_profile(backend):
    # n nodes in series between 300 K and 310 K, each half-link 0.25 K/W: the steady profile is linear,
    # T_i = 300 + 10·(i + 0.5)/n, whatever the capacities
    n = 400
    m = tnn_dsl.compile(_chain(n), backend)
    assert m.sparse and n >= SPARSE_MIN_STATES
    T = m.xp.to_numpy(m.steady_state(m.init_params(), np.zeros(0)))
    np.testing.assert_allclose(T, 300.0 + 10.0 * (np.arange(n) + 0.5) / n, rtol=0, atol=1e-9)


def test_a_sparse_model_holds_no_dense_n_by_n_array():
    n = 3000
    m = tnn_dsl.compile(_chain(n), "jax")
    assert m.sparse
    for name, v in vars(m._core).items():
        size = getattr(v, "size", 0) if not isinstance(v, SparseMatrix) else v.nnz
        assert int(size) < 10 * n, name
    prep = m._core.prepare(m._packed(m.init_params()))
    assert isinstance(prep.L, SparseMatrix) and prep.L.nnz <= 4 * (n + 1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_generated_plate_is_sparse_by_default_and_matches_the_dense_reference(backend):
    net = tnn_dsl.loads(plate_thn(16, 14), "plate.thn")
    assert len(net.nodes) == 224 >= SPARSE_MIN_STATES
    m = tnn_dsl.compile(net, backend)
    ref = tnn_dsl.compile(net, "numpy", sparse=False)
    assert m.sparse
    u = np.zeros((50, len(net.inputs)))
    u[:, 0] = 293.15
    u[:, 1:] = 20.0
    T0 = np.full(len(m.state_names), 293.15)
    s, y = m.rollout(m.init_params(), T0, u, 1.0)
    s_ref, _ = ref.rollout(ref.init_params(), T0, u, 1.0)
    assert np.max(np.abs(m.xp.to_numpy(s) - s_ref)) <= 1e-9
    # heat balance: the heaters' energy is in the plate or lost to ambient (nothing made up by the scatter)
    assert float(np.max(m.xp.to_numpy(s)[-1])) > 293.2


def test_packed_constants_follow_new_values():
    import jax.numpy as jnp

    m = tnn_dsl.compile(_chain(100), "jax")
    p = m.init_params()
    u = np.zeros((5, 0))
    T0 = np.full(100, 305.0)
    s1 = np.asarray(m.rollout(p, T0, u, 1.0, substeps=5)[0])
    s1b = np.asarray(m.rollout(p, T0, u, 1.0, substeps=5)[0])
    p2 = dict(p)
    p2["TL"] = jnp.asarray(200.0)
    s2 = np.asarray(m.rollout(p2, T0, u, 1.0, substeps=5)[0])
    np.testing.assert_array_equal(s1, s1b)
    assert s2[-1, 0] < s1[-1, 0] - 1.0  # the new boundary value reached the first node
    T_ss = np.asarray(m.steady_state(p2, u[0]))
    assert T_ss[0] < 210.0


def test_sparse_matrix_primitives():
    coo = Coo((4, 3))
    for r, c, v in ((0, 0, 1.0), (3, 2, -2.0), (1, 0, 0.5), (3, 2, 1.0), (2, 1, 4.0)):
        coo.add(r, c, v)
    x = np.arange(8.0).reshape(2, 4)
    for backend in ("numpy", "jax", "torch"):
        from tnn_dsl.compiler.backends import get_xp

        xp = get_xp(backend)
        S = as_matrix(xp, coo, True)
        np.testing.assert_allclose(xp.to_numpy(S.rmatmul(xp.asarray(x))), x @ coo.dense())
        np.testing.assert_allclose(xp.to_numpy(S.select_rows(1, 4).rmatmul(xp.asarray(x[:, 1:]))),
                                   x[:, 1:] @ coo.dense()[1:])
        np.testing.assert_allclose(xp.to_numpy(S.diagonal(3)), np.diag(coo.dense()[:3]))


@settings(max_examples=25, deadline=None)
@given(nx=st.integers(1, 9), ny=st.integers(1, 9), heaters=st.integers(0, 3), sensors=st.integers(0, 3))
def test_plate_generator_parses_to_the_mesh(nx, ny, heaters, sensors):
    net = tnn_dsl.loads(plate_thn(nx, ny, heaters=heaters, sensors=sensors), "p.thn")
    n = nx * ny
    assert len(net.nodes) == n
    assert len(net.links) == (nx - 1) * ny + nx * (ny - 1) + n
    assert len(net.inputs) == 1 + min(heaters, n)
    assert len(net.sensors) == min(sensors, n)


@settings(max_examples=15, deadline=None)
@given(zones=st.integers(1, 40))
def test_building_generator_parses(zones):
    net = tnn_dsl.loads(building_thn(zones), "b.thn")
    assert len(net.nodes) == 2 * zones
    assert len(net.sources) == zones
    assert len(net.sensors) == len(range(0, zones, 8))


def test_plate_size():
    assert plate_size(10_000) == (100, 100)
    assert plate_size(1) == (1, 1)
    nx, ny = plate_size(20_000)
    assert abs(nx * ny - 20_000) < 150
    with pytest.raises(ValueError):
        plate_thn(0, 3)


def test_tnnc_generate_plate_and_building(tmp_path, capsys):
    from tnn_dsl.cli import main

    out = tmp_path / "plate.thn"
    assert main(["generate", "plate", "--size", "50", "-o", str(out)]) == 0
    net = tnn_dsl.load(str(out))
    assert len(net.nodes) == 49
    assert main(["check", str(out)]) == 0
    b = tmp_path / "b.thn"
    assert main(["generate", "building", "--size", "12", "-o", str(b)]) == 0
    assert len(tnn_dsl.load(str(b)).nodes) == 24
    # an existing file of another kind is not overwritten without --force
    other = tmp_path / "data.csv"
    other.write_text("t,T\n0,1\n")
    assert main(["generate", "plate", "--size", "4", "-o", str(other)]) == 1
    assert other.read_text() == "t,T\n0,1\n"
    assert main(["generate", "plate", "--size", "0", "-o", str(tmp_path / "z.thn")]) == 1
    assert "--size must be" in capsys.readouterr().err


def test_gauss_newton_step_in_readings_space_equals_the_stacked_least_squares():
    from tnn_dsl.fit.initial import gauss_newton_step

    rng = np.random.default_rng(3)
    for m, n in ((30, 200), (5, 6), (40, 41)):
        J = rng.normal(size=(m, n))
        r = rng.normal(size=m)
        W = rng.uniform(0.5, 2, m)
        P = rng.uniform(0.1, 1, n)
        d = rng.normal(size=n)
        A = np.vstack([J * W[:, None], np.diag(P)])
        b = np.concatenate([-r * W, -P * d])
        ref = np.linalg.lstsq(A, b, rcond=None)[0]
        np.testing.assert_allclose(gauss_newton_step(J, r, W, P, d), ref, rtol=0, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_initial_state_of_a_large_network_by_reverse_mode(backend):
    # a 225-node plate seen by three sensors: more unknowns (225) than burn-in readings (3 × 30), so the
    # readings' sensitivities come from reverse mode; they equal forward mode, and the estimate fits the burn-in
    from tnn_dsl.data import Experiment
    from tnn_dsl.fit.initial import _BurnInFit, initial_state

    net = tnn_dsl.loads(plate_thn(15, 15), "plate.thn")
    m = tnn_dsl.compile(net, backend)
    p = m.init_params()
    N = 120
    U = np.zeros((N, 3))
    U[:, 0] = 293.15
    U[:, 1] = np.where((np.arange(N) // 40) % 2, 30.0, 0.0)
    U[:, 2] = 10.0
    T0 = 293.15 + 4.0 * np.sin(np.linspace(0, 3, len(m.state_names)))
    _, y = m.rollout(p, T0, U, 1.0)
    y = np.asarray(m.xp.to_numpy(y))
    fit = _BurnInFit(m, 1.0, 30, "rk4", None)
    J_rev = np.asarray(m.xp.to_numpy(fit.fJ(p, m.xp.asarray(U[:30]), m.xp.asarray(T0))))
    from tnn_dsl.compiler.backends.adapter import backend_of

    B = backend_of(m)
    J_fwd = B.jacobian(lambda T: m.rollout(p, T, B.asarray(U[:30]), 1.0)[1], T0)
    assert J_rev.shape == (30, 3, 225)
    np.testing.assert_allclose(J_rev, J_fwd, rtol=0, atol=1e-12)
    exp = Experiment(name="plate", path="", t=np.arange(N, dtype=float), dt=1.0, inputs=U, outputs=y,
                     input_names=tuple(m.input_names), output_names=tuple(m.output_names))
    ini = initial_state(net, m, p, exp, "estimate", burn_in_s=30.0)
    _, y_hat = m.rollout(p, ini.T, U, 1.0)
    err = np.abs(np.asarray(m.xp.to_numpy(y_hat))[:30] - y[:30])
    assert ini.rule == "estimate" and float(err.max()) < 0.05
    # the free run (its jitted rollout takes the packed table) gives the same run as the model's own rollout
    from tnn_dsl.fit.simulation import free_run

    run = free_run(m, p, exp, "estimate", burn_in_s=30.0)
    np.testing.assert_allclose(run.y, np.asarray(m.xp.to_numpy(y_hat)), rtol=0, atol=1e-9)
