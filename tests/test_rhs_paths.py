"""The fast right-hand side (input-only work hoisted out of the time loop, affine node terms, vectorised
learned targets) against an independent assembly from the per-element heat flows.

``model.rhs`` is ``rhs_T(rhs_u(u), T)``: input-only parameters and every flow whose coefficients depend on
the inputs alone are reduced once per sample to ``q + d·T`` per node, learned parameter targets are
evaluated as one vector, and links driven by them gather that vector. ``model.heat_flows`` computes each
element's flow with the plain physics functions. Summing the flows into each node and dividing by its
capacity must give the same right-hand side, with and without ``scale:`` keys, on networks that put every
component on both sides of the split (Peltier on a boundary, input-driven boundaries read by a lagged
sensor, input-dependent fluid flow, learned flows and heat loads)."""

from __future__ import annotations

import contextlib

import numpy as np
import pytest
from nets import B, case_inputs, case_study, peltier_fluid, ref, two_node

import tnn_dsl
from tnn_dsl.compiler.backends.adapter import forward_only
from tnn_dsl.ir.network import Binary, Num


def boundary_net():
    """Input-driven boundaries on every element kind's side; everything's coefficients input-only."""
    b = B("paths")
    b.input("I")
    b.input("Ta", is_temperature=True)
    b.input("Tf", is_temperature=True)
    b.input("P")
    b.boundary("amb", ref("Ta"))
    b.boundary("sink", 290.0)
    b.node("h", 40.0)
    b.node("c", 30.0)
    b.node("m", 200.0)
    b.R("h", "amb", 0.5)
    b.G("c", "m", 0.8)
    b.R("m", "sink", 4.0)
    b.peltier("pe", "amb", "c", ref("I"), 0.04, 1.5)  # hot side on an input-driven boundary
    b.peltier("pe2", "h", "c", Binary(op="*", left=Num(value=0.5), right=ref("I")), 0.05, 2.0, r_internal=1.5)
    b.fluid("f1", "m", ref("Tf"), Binary(op="*", left=Num(value=0.001), right=ref("P")), 4186.0, 5.0)
    b.source("m", ref("P"))
    b.radiation("m", "amb", area=0.05, emissivity=0.8)
    b.sensor("Tamb", "amb", lag=7.0, offset=0.2)
    b.sensor("Tm", "m", lag=3.0)
    return b.build()


def wall_u():
    """Two nodes and a wall at a constant 290 K; the resistance node 1–wall learned linear in the input ``P`` W."""
    b = B("wall_u")
    b.input("P")
    b.boundary("wall", 290.0)
    b.node("n1", 100.0)
    b.node("n2", 300.0)
    b.R("n1", "wall", 2.0, name="R_w1")
    b.G("n1", "n2", 0.8)
    b.R("n2", "wall", 4.0)
    b.source("n1", ref("P"))
    b.sensor("T2", "n2")
    b.learn("f_w", "linear", ["R_w1"], ["P"])
    return b.build()


NETS = {
    "boundaries": (boundary_net, lambda rng, n: np.stack(
        [rng.uniform(0, 3, n), rng.uniform(285, 305, n), rng.uniform(280, 300, n), rng.uniform(1, 2, n)], -1)),
    "peltier_fluid": (peltier_fluid, lambda rng, n: np.stack([rng.uniform(0, 3, n), rng.uniform(280, 300, n)], -1)),
    "two_node": (two_node, lambda rng, n: np.stack([rng.uniform(285, 305, n), rng.uniform(0, 20, n)], -1)),
    # linear and MLP learned functions of node temperatures: their first layer is folded into the one
    # T-linear product of the right-hand side (``_Core._fold``); heat_flows evaluates them unfolded
    "m2_extra": (lambda: case_study("linear", extra=True),
                 lambda rng, n: case_inputs(600, seed=2)[rng.integers(0, 600, n)]),
    "m3_extra": (lambda: case_study("mlp", extra=True),
                 lambda rng, n: case_inputs(600, seed=3)[rng.integers(0, 600, n)]),
    "m4_extra": (lambda: case_study("mlp_peltier", extra=True),
                 lambda rng, n: case_inputs(600, seed=4)[rng.integers(0, 600, n)]),
    # links whose conductances depend on the inputs alone: made with the sample's context (``"gD"``); on JAX traced
    # forward only (``forward_only``) put in place in the node matrix of each right-hand side (``m2_u1``), else
    # gathered and scattered (``m2_u1_scatter``: a model over ``assembly.NODE_MATRIX_MAX``, set to 0 for it)
    "m2_u1": (lambda: case_study("linear_u1"), lambda rng, n: case_inputs(600, seed=5)[rng.integers(0, 600, n)]),
    "m2_u1_scatter": (lambda: case_study("linear_u1"),
                      lambda rng, n: case_inputs(600, seed=5)[rng.integers(0, 600, n)]),
    # links owned by two functions of node temperatures: one gather of their target vectors put end to end
    # (``_links_vec``), the targets interleaved in the links' order
    "two_fns": (lambda: case_study("two_fns"), lambda rng, n: case_inputs(600, seed=6)[rng.integers(0, 600, n)]),
    # the same with a constant boundary at a learned link's end (its heat folded into the input-only heat q)
    "wall_u": (lambda: wall_u(), lambda rng, n: rng.uniform(0, 20, (n, 1))),
}


def random_table(model, seed):
    rng = np.random.default_rng(seed)
    p = model.to_numpy(model.init_params(seed))
    for k, spec in model.param_specs.items():
        if spec.kind == "weights":
            p[k] = rng.uniform(-0.3, 0.3, size=spec.shape)
    return p


def assembled_rhs(model, p, T, u):
    """dT/dt from ``heat_flows`` summed per node (numpy, float64)."""
    P = model._plan
    flows = {k: np.asarray(model.xp.to_numpy(v), dtype=float) for k, v in model.heat_flows(
        model.from_numpy(p), model.xp.asarray(T), model.xp.asarray(u)).items()}
    n = P.n
    Q = np.zeros(T.shape[:-1] + (n,))

    def into(v, q):
        if v[0] == "n":
            Q[..., v[1]] += q

    for key, a, b, *_ in P.links + P.rads:
        into(a, flows[key])
        into(b, -flows[key])
    for pe, h, c in P.peltiers:
        into(h, flows[f"{pe.name}.Q_hot"])
        into(c, flows[f"{pe.name}.Q_cold"])
    for f in P.fluids:
        Q[..., P.node_idx[f.node]] += flows[f"{f.name}.Q"]
    for s in model.network.sources:
        Q[..., P.node_idx[s.node]] += flows[f"{s.name}.Q"]
    for node in P.heat_loads:
        Q[..., P.node_idx[node]] += flows[f"Q[{node}]"]
    def val(name):  # a constant parameter's value with its scale
        return float(p[name]) * float(p.get(f"scale:{name}", 1.0))

    C = np.array([val(nd.capacitance) for nd in model.network.nodes])
    dT = Q / C
    lag = []
    for k, s in enumerate(P.lagged):
        # a boundary sensor in these nets reads an input-driven boundary (``amb = Ta``, input 1)
        src = (T[..., P.node_idx[s.node]] if s.node in P.node_idx
               else u[..., model.input_names.index("Ta")] * float(p.get("scale:T_amb", 1.0)))
        lag.append((src - T[..., n + k]) / val(s.lag))
    return np.concatenate([dT, np.stack(lag, -1)], -1) if lag else dT


@pytest.mark.parametrize("backend", ["jax", "torch"])
@pytest.mark.parametrize("name", sorted(NETS))
@pytest.mark.parametrize("scaled", [False, True])
def test_rhs_equals_sum_of_heat_flows(backend, name, scaled, monkeypatch):
    build, draw = NETS[name]
    net = build()
    if name == "m2_u1_scatter":
        monkeypatch.setattr("tnn_dsl.compiler.assembly.NODE_MATRIX_MAX", 0)
    model = tnn_dsl.compile(net, backend)
    in_matrix = name in ("m2_u1", "wall_u") and backend == "jax"
    if name.startswith("m2_u1") or name == "wall_u":  # the path this net is here for
        core = model._core
        assert core._links_d_u and "gD" in core.rhs_u(model._prepare(model.init_params()),
                                                      model.xp.asarray(draw(np.random.default_rng(0), 2)))["v"]
        assert core.links_in_matrix is in_matrix
        assert [k for k, _ in core._L_blocks] == ["M", "D"]
    if name == "two_fns":
        assert model._core._links_vec[0] == ("f2_bs", "f1_hp") and model._core._links_vec[1] is not None
    p = random_table(model, 0)
    rng = np.random.default_rng(1)
    if scaled:  # every scale key at a random value: parameters, flows, learned targets
        for k in model.scale_keys:
            p[k] = np.asarray(rng.uniform(0.8, 1.25))
    B_ = 5
    T = 298.15 + rng.normal(0, 4, size=(B_, len(model.state_names)))
    u = draw(rng, B_)
    if name == "boundaries":  # lag state of the boundary sensor starts near the boundary
        T[:, -2] = u[:, 1] + rng.normal(0, 1, B_)
    with forward_only() if in_matrix else contextlib.nullcontext():
        got = np.asarray(model.xp.to_numpy(model.rhs(model.from_numpy(p), model.xp.asarray(T), model.xp.asarray(u))))
        if in_matrix:
            assert model._core._in_matrix()
    want = assembled_rhs(model, p, T, u)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", ["jax", "torch"])
@pytest.mark.parametrize("integrator", ["euler", "rk4", "expeuler"])
def test_rollout_steps_match_rhs(backend, integrator):
    """A rollout (sequence context, one sample per step) equals stepping with ``model.rhs`` by hand."""
    from tnn_dsl.compiler.integrators import euler, expeuler, rk4

    model = tnn_dsl.compile(boundary_net(), backend)
    p = model.from_numpy(random_table(model, 2))
    rng = np.random.default_rng(5)
    U = NETS["boundaries"][1](rng, 6)
    T0 = 298.15 + rng.normal(0, 2, size=len(model.state_names))
    dt = 0.5
    states, _ = model.rollout(p, model.xp.asarray(T0), model.xp.asarray(U), dt, integrator, substeps=1)
    T = model.xp.asarray(T0)
    for k in range(5):
        u = model.xp.asarray(U[k])
        if integrator == "expeuler":
            T = expeuler(lambda x: model.rhs_and_diag(p, x, u), T, dt, model.xp)
        else:
            T = (euler if integrator == "euler" else rk4)(lambda x: model.rhs(p, x, u), T, dt)
        np.testing.assert_allclose(np.asarray(model.xp.to_numpy(states))[k + 1], np.asarray(model.xp.to_numpy(T)),
                                   rtol=0, atol=1e-11)


@pytest.mark.parametrize("backend", ["jax", "torch"])
def test_diag_is_jacobian_diagonal(backend):
    """``rhs_and_diag``'s diagonal equals the Jacobian's where nothing learned depends on the state
    (Peltier sides on boundaries and nodes, an input-dependent fluid, radiation, boundary lags)."""
    model = tnn_dsl.compile(boundary_net(), backend)
    pn = random_table(model, 0)
    p = model.from_numpy(pn)
    rng = np.random.default_rng(7)
    T = 298.15 + rng.normal(0, 3, size=len(model.state_names))
    u = NETS["boundaries"][1](rng, 1)[0]
    _, d = model.rhs_and_diag(p, model.xp.asarray(T), model.xp.asarray(u))
    Tt, ut = model.xp.asarray(T), model.xp.asarray(u)
    if backend == "jax":
        import jax

        J = np.asarray(jax.jacfwd(lambda x: model.rhs(p, x, ut))(Tt))
    else:
        import torch

        J = torch.func.jacfwd(lambda x: model.rhs(p, x, ut))(Tt).numpy()
    np.testing.assert_allclose(np.asarray(model.xp.to_numpy(d)), np.diag(J), rtol=1e-10, atol=1e-14)
