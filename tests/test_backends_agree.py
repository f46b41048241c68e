"""Torch and JAX give the same rollouts and gradients (issue 3 acceptance: ≤ 1e-9 K, gradients 1e-6 rel)."""

from __future__ import annotations

import nets
import numpy as np
import pytest

import tnn_dsl


def _rollouts_and_grads(net, N, integrator="rk4", seed=0):
    import jax
    import torch

    mj = tnn_dsl.compile(net, "jax")
    mt = tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(mj, seed)
    u = nets.case_inputs(N, seed=1)
    T0 = np.full(len(mj.state_names), 298.15) + np.linspace(-2, 2, len(mj.state_names))
    w = np.random.default_rng(seed + 1).standard_normal((N, len(mj.output_names)))

    def loss_j(p):
        _, y = mj.rollout(p, T0, u, 1.0, integrator=integrator)
        return (y * w).sum() / N

    pj = mj.from_numpy(p_np)
    sj, yj = mj.rollout(pj, T0, u, 1.0, integrator=integrator)
    gj = jax.grad(loss_j)(pj)

    pt = {k: v.requires_grad_(True) for k, v in mt.from_numpy(p_np).items()}
    st, yt = mt.rollout(pt, T0, u, 1.0, integrator=integrator)
    (yt * torch.as_tensor(w)).sum().div(N).backward()
    gt = {k: v.grad for k, v in pt.items()}
    return (np.asarray(sj), np.asarray(yj), {k: np.asarray(v) for k, v in gj.items()},
            st.detach().numpy(), yt.detach().numpy(), {k: (np.zeros(pt[k].shape) if v is None else v.numpy())
                                                          for k, v in gt.items()})


def _check(net, N, integrator="rk4"):
    sj, yj, gj, st, yt, gt = _rollouts_and_grads(net, N, integrator)
    assert np.max(np.abs(sj - st)) <= 1e-9
    assert np.max(np.abs(yj - yt)) <= 1e-9
    assert set(gj) == set(gt)
    scale = max(np.max(np.abs(g)) for g in gj.values())
    nonzero = 0
    for k in gj:
        a, b = gj[k], gt[k]
        err = np.max(np.abs(a - b)) if a.size else 0.0
        assert err <= 1e-6 * max(np.max(np.abs(a)) if a.size else 0.0, 1e-8 * scale), (k, a, b)
        nonzero += bool(a.size and np.any(a != 0))
    assert nonzero >= len(gj) // 2  # the gradient really flows to the parameters


@pytest.mark.parametrize("learn", ["mlp", "mlp_peltier"])
def test_case_study_all_components_agree_short(learn):
    # fast CI variant: 10 minutes of the case study with every component kind
    _check(nets.case_study(learn, extra=True), 600)


def test_input_only_links_agree_short():
    """The doctor's answer on the case study (the heat pipe's resistances linear in u1): their conductances made
    once per sample with the input-only context, rollouts and gradients the same on both backends; and JAX's rollout
    traced forward only (``Backend.no_grad``: the links in place in the node matrix, ``assembly.NODE_MATRIX_MAX``)
    the same as the one it differentiates."""
    from tnn_dsl.compiler.backends.adapter import Backend

    net = nets.case_study("linear_u1")
    _check(net, 600)
    _check(net, 300, integrator="expeuler")
    m = tnn_dsl.compile(net, "jax")
    assert m._core.links_in_matrix
    p = m.from_numpy(nets.random_params(m, 3))
    u = nets.case_inputs(600, seed=3)
    T0 = np.full(len(m.state_names), 298.15)
    for integrator in ("rk4", "expeuler"):
        a = np.asarray(m.rollout(p, T0, u, 1.0, integrator=integrator)[0])
        b = np.asarray(Backend("jax").jit(Backend("jax").no_grad(
            lambda pp: m.rollout(pp, T0, u, 1.0, integrator=integrator)[0]))(p))
        assert np.max(np.abs(a - b)) <= 1e-9, integrator
        assert np.max(np.abs(a - a[0])) > 1.0  # it moved


def test_an_eager_torch_rollout_without_gradients_returns_ordinary_tensors_and_leaves_nothing_behind():
    """Torch's eager step loop runs under ``torch.inference_mode()`` when nothing is differentiated (issue 18): its
    states and outputs come back as ordinary tensors (a caller may differentiate through them later), JAX's to
    1e-9 K, and a rollout with gradients on the same model afterwards (its caches filled by the first) differentiates
    as JAX's."""
    import jax
    import jax.numpy as jnp
    import torch

    net = nets.case_study("mlp", extra=True)
    mt, mj = tnn_dsl.compile(net, "torch"), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 0)
    u = nets.case_inputs(50, seed=1)
    T0 = np.full(len(mj.state_names), 298.15)
    with torch.no_grad():
        s, y = mt.rollout(mt.from_numpy(p_np), T0, u, 1.0)
    assert not s.is_inference() and not y.is_inference()
    assert np.max(np.abs(s.numpy() - np.asarray(mj.rollout(mj.from_numpy(p_np), T0, u, 1.0)[0]))) <= 1e-9
    T0t = torch.as_tensor(T0).requires_grad_(True)
    (s * 1.0 + mt.rollout(mt.from_numpy(p_np), T0t, u, 1.0)[0]).sum().backward()  # no "inference tensor" error
    pj = mj.from_numpy(p_np)
    want = np.asarray(jax.grad(lambda T: mj.rollout(pj, T, u, 1.0)[0].sum())(jnp.asarray(T0)))
    assert np.max(np.abs(T0t.grad.numpy() - want)) <= 1e-6 * np.max(np.abs(want))


def test_case_study_agree_expeuler_short():
    _check(nets.case_study("mlp", extra=True), 300, integrator="expeuler")


@pytest.mark.slow
def test_case_study_all_components_agree_4h():
    _check(nets.case_study("mlp", extra=True), 4 * 3600)


def test_steady_state_and_its_gradient_agree():
    import jax

    net = nets.case_study("mlp", extra=True)
    mj, mt = tnn_dsl.compile(net, "jax"), tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(mj, 2)
    u = np.array([[2.0, 0.3, 295.15, 298.15, 298.15], [1.0, 0.8, 290.0, 300.0, 298.0]])
    pj = mj.from_numpy(p_np)
    Tj = np.asarray(mj.steady_state(pj, u))
    f = np.asarray(mj.rhs(pj, Tj, u))
    assert np.max(np.abs(f)) < 1e-10
    gj = jax.grad(lambda p: mj.steady_state(p, u)[:, 5].sum())(pj)
    pt = {k: v.requires_grad_(True) for k, v in mt.from_numpy(p_np).items()}
    Tt = mt.steady_state(pt, u)
    np.testing.assert_allclose(Tt.detach().numpy(), Tj, rtol=0, atol=1e-9)
    Tt[:, 5].sum().backward()
    scale = max(float(np.max(np.abs(np.asarray(g)))) for g in gj.values())
    for k, spec in mj.param_specs.items():
        a = np.asarray(gj[k])
        b = np.zeros(spec.shape) if pt[k].grad is None else pt[k].grad.numpy()
        # capacities do not move a steady state: their gradient is round-off on both sides
        assert np.max(np.abs(a - b)) <= 1e-6 * max(np.max(np.abs(a)), 1e-8 * scale), k
    # the implicit derivative matches a finite difference of the converged solution
    h = 1e-6
    for name in ("pe.seebeck", "R_hp2", "f2.UA"):
        q1, q2 = dict(p_np), dict(p_np)
        q1[name] = p_np[name] * (1 + h)
        q2[name] = p_np[name] * (1 - h)
        fd = (np.asarray(mj.steady_state(mj.from_numpy(q1), u))[:, 5].sum()
              - np.asarray(mj.steady_state(mj.from_numpy(q2), u))[:, 5].sum()) / (2 * h * p_np[name])
        assert float(gj[name]) == pytest.approx(fd, rel=1e-5, abs=1e-9), name


def test_torch_newton_difference_jacobian_and_its_steady_state():
    """torch's steady state iterates Newton with a central-difference Jacobian (one batched call of the right-hand
    side instead of ``torch.func.jacfwd``, issue 18): on the case study with its MLP heat pipe and radiation the
    difference Jacobian is the exact one to 1e-5 relative, batched or not, and the steady state is JAX's to 1e-9 K
    without a gradient (the last step's Jacobian is then the difference one too) as with one."""
    import torch

    net = nets.case_study("mlp", extra=True)
    mj, mt = tnn_dsl.compile(net, "jax"), tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(mj, 3)
    prep = mt._prepare(mt.from_numpy(p_np))
    rng = np.random.default_rng(0)
    T = torch.as_tensor(300.0 + 5.0 * rng.random((2, 3, len(mt.state_names))))
    u = torch.as_tensor(np.array([2.0, 0.3, 295.15, 298.15, 298.15]) * (1 + 0.1 * rng.random((2, 3, 5))))
    with torch.no_grad():
        exact, diff = mt._jac(prep, T, u), mt._jac(prep, T, u, exact=False)
    assert diff.shape == exact.shape == (2, 3, len(mt.state_names), len(mt.state_names))
    assert float((diff - exact).abs().max()) <= 1e-5 * float(exact.abs().max())
    uu = np.array([[2.0, 0.3, 295.15, 298.15, 298.15], [1.0, 0.8, 290.0, 300.0, 298.0]])
    Tj = np.asarray(mj.steady_state(mj.from_numpy(p_np), uu))
    with torch.no_grad():
        Tt = mt.steady_state(mt.from_numpy(p_np), uu)
    np.testing.assert_allclose(Tt.numpy(), Tj, rtol=0, atol=1e-9)


def test_parsed_networks_agree():
    """The shipped case-study files compile to the same model on both backends."""
    import os

    root = os.path.join(os.path.dirname(__file__), "..", "networks", "peltier_heatpipe")
    for name in ("m2.thn", "m4.thn"):
        net = tnn_dsl.load(os.path.join(root, name))
        mj, mt = tnn_dsl.compile(net, "jax"), tnn_dsl.compile(net, "torch")
        p_np = nets.random_params(mj, 5)
        N = 200
        u = np.zeros((N, len(mj.input_names)))
        for j, inp in enumerate(net.inputs):
            u[:, j] = 298.15 if inp.is_temperature else np.linspace(0.0, 2.0, N)
        T0 = np.full(len(mj.state_names), 298.15)
        sj, _ = mj.rollout(mj.from_numpy(p_np), T0, u, 1.0)
        st, _ = mt.rollout(mt.from_numpy(p_np), T0, u, 1.0)
        assert np.max(np.abs(np.asarray(sj) - st.numpy())) <= 1e-9, name
