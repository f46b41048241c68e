"""Torch rollouts through ``torch.compile`` (``compile(..., torch_compile=True)``, issue 3's "torch within 5× of
JAX"): the same states and gradients as eager torch and as JAX, recompilation for new window lengths, the
eager fallback when torch cannot compile, and the switches (argument, ``TNN_TORCH_COMPILE``, CLI flags)."""

from __future__ import annotations

import warnings
from pathlib import Path

import nets
import numpy as np
import pytest

import tnn_dsl
import tnn_dsl.compiler.model as M
from tnn_dsl import TnnError

torch = pytest.importorskip("torch")


SMALL = """\
network small "a Peltier element, a fluid and an MLP-learned resistance: every kind of flow the compiler emits"
units temperature = degC
input I  : [A]
input u1 : [1]
input Ta : temperature
input Tf1 : temperature
node h  C = 40 J/K
node c  C = 40 J/K
node s  C = 300 J/K
boundary amb = Ta
R h -- s   = 0.1 K/W
R s -- amb = 0.5 K/W  as R_sa
R c -- amb = 4 K/W
peltier pe  hot = h  cold = c  current = I  seebeck = 0.05 V/K free  resistance = 2 ohm  R_internal = 1.5 K/W
fluid f1  through c  inlet = Tf1  mdot = 0.002 kg/s  cp = 4186 J/(kg*K)  UA = 5 W/K
sensor T_c = c
learn R_sa as mlp(s, u1; hidden = [4], activation = sigmoid)
"""


def _torch_run(model, p_np, T0, U, integrator="rk4"):
    """States, outputs and the gradient of a weighted output sum w.r.t. every parameter (numpy)."""
    p = {k: v.requires_grad_(True) for k, v in model.from_numpy(p_np).items()}
    s, y = model.rollout(p, torch.as_tensor(T0), torch.as_tensor(U), 1.0, integrator=integrator)
    w = torch.linspace(-1.0, 1.0, y.numel(), dtype=y.dtype).reshape(y.shape)
    (y * w).sum().backward()
    grads = {k: (np.zeros(v.shape) if v.grad is None else v.grad.numpy()) for k, v in p.items()}
    return s.detach().numpy(), y.detach().numpy(), grads


def _jax_run(model, p_np, T0, U, integrator="rk4"):
    import jax
    import jax.numpy as jnp

    def loss(p):
        _, y = model.rollout(p, T0, U, 1.0, integrator=integrator)
        w = jnp.linspace(-1.0, 1.0, y.size).reshape(y.shape)
        return (y * w).sum()

    p = model.from_numpy(p_np)
    s, y = model.rollout(p, T0, U, 1.0, integrator=integrator)
    return np.asarray(s), np.asarray(y), {k: np.asarray(v) for k, v in jax.grad(loss)(p).items()}


def _assert_same(a, b, *, atol=1e-9, grad_rtol=1e-6):
    (sa, ya, ga), (sb, yb, gb) = a, b
    assert np.max(np.abs(sa - sb)) <= atol
    assert np.max(np.abs(ya - yb)) <= atol
    scale = max(float(np.max(np.abs(g))) for g in ga.values() if g.size)
    for k in ga:
        if ga[k].size:
            assert np.max(np.abs(ga[k] - gb[k])) <= grad_rtol * max(float(np.max(np.abs(ga[k]))), 1e-8 * scale), k


def _batch(model, N, B=3, seed=1):
    """``T0 (B, n_states)`` K and ``U (B, N, n_inputs)``: the case-study input columns the model takes."""
    order = ("I", "u1", "Ta", "Tf1", "Tf2")
    U = np.stack([nets.case_inputs(N, seed=seed + b) for b in range(B)])
    cols = {"Tf": "Tf1"}
    U = U[..., [order.index(cols.get(name, name)) for name in model.input_names]]
    n = len(model.state_names)
    T0 = 298.15 + np.linspace(-2, 2, n) + np.arange(B)[:, None] * 0.3
    return T0, U


def test_compiled_torch_matches_eager_and_jax_and_recompiles_for_new_windows():
    """One compiled model against eager torch and JAX: states, outputs and every gradient on a batch; then (forward
    only, to keep CI short) another window length and batch size from one initial state: a new graph, not stale
    shapes, and ``T0 (n_states,)`` broadcast to the batch, a view with a stride of 0 that the compiled scan refused
    as its carry ("differ in 'stride: (0, 1)'"), after which the model had warned and run eager for good."""
    net = tnn_dsl.loads(SMALL, "small.thn")
    mc = tnn_dsl.compile(net, "torch", torch_compile=True)
    me, mj = tnn_dsl.compile(net, "torch"), tnn_dsl.compile(net, "jax")
    assert mc.torch_compile and not me.torch_compile
    p_np = nets.random_params(mj, 3)
    T0, U = _batch(mj, 12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)  # it really compiled
        got = _torch_run(mc, p_np, T0, U)
        _assert_same(_torch_run(me, p_np, T0, U), got)
        _assert_same(_jax_run(mj, p_np, T0, U), got)
        T0, U = _batch(mj, 7, B=2)
        with torch.no_grad():
            s, y = mc.rollout(mc.from_numpy(p_np), torch.as_tensor(T0[0]), torch.as_tensor(U), 1.0)
            s_e, y_e = me.rollout(me.from_numpy(p_np), torch.as_tensor(T0[0]), torch.as_tensor(U), 1.0)
    s_j, y_j = mj.rollout(mj.from_numpy(p_np), T0[0], U, 1.0)
    assert mc.torch_compile
    for s_ref, y_ref in ((s_e.numpy(), y_e.numpy()), (np.asarray(s_j), np.asarray(y_j))):
        assert np.max(np.abs(s.numpy() - s_ref)) <= 1e-9 and np.max(np.abs(y.numpy() - y_ref)) <= 1e-9


def _param_sets_case():
    """The compiled, eager and JAX models of ``SMALL``, random parameter sets, their initial states and inputs, and
    ``want(n_sets, n)``: JAX's rollout of each of the first sets over the first ``n`` samples, stacked."""
    net = tnn_dsl.loads(SMALL, "small.thn")
    mc, mj, me = (tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax"),
                  tnn_dsl.compile(net, "torch"))
    sets = [nets.random_params(mj, seed) for seed in range(3, 5 + M.TORCH_PARAM_BATCH)]
    T0s, U = _batch(mj, 40, B=len(sets))
    U = U[0]

    def want(n_sets, n):
        runs = [mj.rollout(mj.from_numpy(p), T0s[b], U[:n], 1.0) for b, p in enumerate(sets[:n_sets])]
        return np.stack([np.asarray(r[0]) for r in runs]), np.stack([np.asarray(r[1]) for r in runs])

    return net, (mc, me, mj), sets, T0s, U, want


def _compiled_sets(mc, sets, T0s, U, want, cases):
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)  # it really compiled
        warnings.filterwarnings("error", message="There is a performance drop")  # vmap tracing's, not the user's
        for n_sets, n in cases:
            with torch.no_grad():
                s, y = mc.rollouts_of([mc.from_numpy(p) for p in sets[:n_sets]], torch.as_tensor(T0s[:n_sets]),
                                      torch.as_tensor(U[:n]), 1.0)
            s_w, y_w = want(n_sets, n)
            assert s.shape == s_w.shape and y.shape == y_w.shape
            assert np.abs(s.numpy() - s_w).max() <= 1e-9 and np.abs(y.numpy() - y_w).max() <= 1e-9
    assert mc.torch_compile


def test_rollouts_of_many_parameter_sets_are_one_rollout_each():
    """``rollouts_of``: one simulation per parameter set over one input sequence (the doctor's difference Jacobians
    on torch). Compiled, the sets run as one scan of the step vmapped over them, ``TORCH_PARAM_BATCH`` at a time
    (fewer padded, more in chunks: one graph); each row is JAX's rollout of its set to 1e-9 K; JAX's and eager torch's
    ``rollouts_of`` (one rollout after another) agree; a wrong ``T0`` is an error that says what it wanted. The slow
    variant below adds a second length and the fallback where the graph cannot compile."""
    _, (mc, me, mj), sets, T0s, U, want = _param_sets_case()
    _compiled_sets(mc, sets, T0s, U, want, ((3, 40), (2 + M.TORCH_PARAM_BATCH, 40)))
    sets, T0s = sets[:4], T0s[:4]
    s_j, y_j = mj.rollouts_of([mj.from_numpy(p) for p in sets], T0s, U, 1.0)
    s_e, _ = me.rollouts_of([me.from_numpy(p) for p in sets], torch.as_tensor(T0s), torch.as_tensor(U), 1.0)
    s_w, y_w = want(4, 40)
    assert np.abs(np.asarray(s_j) - s_w).max() <= 1e-12 and np.abs(np.asarray(y_j) - y_w).max() <= 1e-12
    assert np.abs(s_e.numpy() - s_w).max() <= 1e-9
    with pytest.raises(tnn_dsl.TnnError, match="one row per parameter set"):
        mj.rollouts_of([mj.from_numpy(p) for p in sets], T0s[:2], U, 1.0)


@pytest.mark.slow  # three compilations, ~45 s; the fast variant is the test above
def test_rollouts_of_compiles_each_length_and_falls_back_where_it_cannot_compile():
    """A second rollout length gets a graph of its own (not stale shapes); where the vmapped graph cannot be
    compiled, one warning and the sets one after another, the compiled model's own rollouts untouched."""
    net, (mc, _, _), sets, T0s, U, want = _param_sets_case()
    _compiled_sets(mc, sets, T0s, U, want, ((3, 40), (2, 25)))
    m2 = tnn_dsl.compile(net, "torch", torch_compile=True)
    real = m2._compiled_torch_param_batch

    def broken(*a):
        import tnn_dsl.compiler.torch_adjoint as ta

        orig = ta.CompiledScan.__call__
        ta.CompiledScan.__call__ = lambda self, *args: (_ for _ in ()).throw(RuntimeError("cannot vmap here"))
        try:
            return real(*a)
        finally:
            ta.CompiledScan.__call__ = orig

    m2._compiled_torch_param_batch = broken
    sets, T0s = sets[:4], T0s[:4]
    with torch.no_grad(), pytest.warns(tnn_dsl.TorchCompileWarning, match="cannot vmap here"):
        s2, _ = m2.rollouts_of([m2.from_numpy(p) for p in sets], torch.as_tensor(T0s), torch.as_tensor(U), 1.0)
    assert np.abs(s2.numpy() - want(4, 40)[0]).max() <= 1e-9 and m2.torch_compile
    m2._compiled_torch_param_batch = real
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)  # warned once: the loop, silently
        m2.rollouts_of([m2.from_numpy(p) for p in sets], torch.as_tensor(T0s), torch.as_tensor(U), 1.0)


def test_models_do_not_share_compiled_steps():
    """Two networks of the same shape but different constants, compiled one after the other in one process,
    each give their own eager result (torch caches compiled code per function; the guards must tell them apart)."""
    for R in (2.0, 5.0):
        net = nets.one_node_rc(R=R)
        mc, me = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "torch")
        U = torch.full((15, len(me.input_names)), 3.0, dtype=torch.float64)
        with torch.no_grad():
            a = mc.rollout(mc.init_params(0), torch.tensor([310.0]), U, 1.0)[0]
            b = me.rollout(me.init_params(0), torch.tensor([310.0]), U, 1.0)[0]
        assert torch.equal(a, b), R


@pytest.mark.parametrize("cpp_wrapper, chunk", [(False, 4)])
def test_single_sequence_scan_either_wrapper_matches_jax(monkeypatch, cpp_wrapper, chunk):
    """A single sequence's forward scan built with the Python wrapper, four samples per iteration (the length 11
    then padded to 12 and the extra state dropped), gives JAX's states to 1e-9 K: the wrapper a failing C++ build
    falls back to. (The default, the C++ wrapper one sample per iteration, is the next test's single sequence;
    ``(True, 1)`` here runs the same check on it.)"""
    from tnn_dsl.compiler import model as compiled_model

    monkeypatch.setattr(compiled_model, "TORCH_CPP_WRAPPER", cpp_wrapper)
    monkeypatch.setattr(compiled_model, "TORCH_CHUNK", chunk)
    net = tnn_dsl.loads(SMALL, "small.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 4)
    T0, U = _batch(mj, 11, B=1)
    with warnings.catch_warnings(), torch.no_grad():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        s, y = mc.rollout(mc.from_numpy(p_np), torch.as_tensor(T0[0]), torch.as_tensor(U[0]), 1.0)
    s_ref, y_ref = mj.rollout(mj.from_numpy(p_np), T0[0], U[0], 1.0)
    assert s.shape == (11, len(mj.state_names))
    assert np.max(np.abs(s.numpy() - np.asarray(s_ref))) <= 1e-9
    assert np.max(np.abs(y.numpy() - np.asarray(y_ref))) <= 1e-9
    scans = [v for k, v in mc._jit_cache.items() if isinstance(k, tuple) and k[0] == "torch_scan"]
    assert len(scans) == 1 and scans[0].fallback is None and scans[0].options.get("cpp_wrapper", False) is cpp_wrapper


def test_forward_scan_with_a_learned_function_of_two_heat_flows_matches_jax():
    """One learned function giving two heat flows read inside the step (the case study's M4 learns the Peltier's
    ``Q_hot`` and ``Q_cold`` so): its two output scales were views of one tensor, two aliasing inputs of the
    compiled scan, which torch refused ("Encountered aliasing during higher order op tracing"), so the model
    fell back to eager with a warning. Single sequence and batch, states to 1e-9 K of JAX's; each scan traced
    once (the prepared 0-d values enter as vectors of one, so dynamo does not restart its analysis)."""
    src = SMALL.replace("learn R_sa as mlp(s, u1; hidden = [4], activation = sigmoid)",
                        "learn Q[h], Q[c] as mlp(s, I; hidden = [3])")
    net = tnn_dsl.loads(src, "two_flows.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 6)
    T0, U = _batch(mj, 9, B=2)
    restarts = nets.dynamo_restarts()
    nets.assert_compiled_forward_matches_jax(mc, mj, p_np, T0, U)
    assert mc.torch_compile
    assert nets.dynamo_restarts() == restarts


def _input_only_link_models():
    """A resistance learned as a function of an input alone (the doctor's u1 law on the case study): its conductance
    is made with the sample's input-only context (``"gD"``), inside the compiled graphs too. (compiled torch, JAX)"""
    src = SMALL.replace("learn R_sa as mlp(s, u1; hidden = [4], activation = sigmoid)", "learn R_sa as linear(u1)")
    net = tnn_dsl.loads(src, "input_only_link.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    assert mc._core._links_d_u
    return mc, mj


def test_compiled_torch_with_input_only_link_conductances_matches_jax():
    """The forward rollouts the doctor's torch engine runs (batch and single sequence): states as JAX's to 1e-9 K."""
    mc, mj = _input_only_link_models()
    p_np = nets.random_params(mj, 7)
    T0, U = _batch(mj, 11)
    nets.assert_compiled_forward_matches_jax(mc, mj, p_np, T0, U)
    assert mc.torch_compile


@pytest.mark.slow  # the adjoint's graphs too (~27 s from an empty inductor cache); the fast variant is above
def test_compiled_torch_with_input_only_link_conductances_gradients_match_jax():
    """States, outputs and every gradient on a batch as JAX's (1e-9 K, 1e-6 relative)."""
    mc, mj = _input_only_link_models()
    p_np = nets.random_params(mj, 7)
    T0, U = _batch(mj, 11)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)  # it really compiled
        _assert_same(_jax_run(mj, p_np, T0, U), _torch_run(mc, p_np, T0, U))
    assert mc.torch_compile


@pytest.mark.slow
@pytest.mark.parametrize("reference", ["jax", "torch"])
def test_compiled_torch_case_study_every_component(reference):
    net = nets.case_study("mlp", extra=True)
    mc = tnn_dsl.compile(net, "torch", torch_compile=True)
    mr = tnn_dsl.compile(net, reference)
    p_np = nets.random_params(mr, 0)
    T0, U = _batch(mr, 300)
    run_ref = _jax_run if reference == "jax" else _torch_run
    _assert_same(run_ref(mr, p_np, T0, U), _torch_run(mc, p_np, T0, U))
    T0e, Ue = _batch(mr, 60)
    _assert_same(run_ref(mr, p_np, T0e, Ue, "expeuler"), _torch_run(mc, p_np, T0e, Ue, "expeuler"))


def test_compile_failure_falls_back_to_eager_with_a_warning(monkeypatch):
    def broken(fn, **kw):
        def call(*a, **k):
            raise RuntimeError("no C++ compiler here")
        return call

    monkeypatch.setattr(torch, "compile", broken)
    net = nets.two_node()
    mc = tnn_dsl.compile(net, "torch", torch_compile=True)
    me = tnn_dsl.compile(net, "torch")
    p_np = mc.to_numpy(mc.init_params(0))
    T0, U = np.array([300.0, 296.0]), np.full((20, len(me.input_names)), 1.0)
    with pytest.warns(tnn_dsl.TorchCompileWarning, match="no C.. compiler here"):
        got = _torch_run(mc, p_np, T0, U)
    assert mc.torch_compile is False  # warned once, eager from then on
    _assert_same(_torch_run(me, p_np, T0, U), got, atol=0.0, grad_rtol=0.0)


def test_switches(monkeypatch):
    net = nets.two_node()
    monkeypatch.setenv("TNN_TORCH_COMPILE", "1")
    assert tnn_dsl.compile(net, "torch").torch_compile is True
    assert tnn_dsl.compile(net, "torch", torch_compile=False).torch_compile is False
    assert tnn_dsl.compile(net, "jax").torch_compile is False  # JAX is always compiled; the flag is torch's
    monkeypatch.setenv("TNN_TORCH_COMPILE", "yes")
    with pytest.raises(TnnError, match="TNN_TORCH_COMPILE must be 0 or 1"):
        tnn_dsl.compile(net, "torch")
    monkeypatch.delenv("TNN_TORCH_COMPILE")
    assert tnn_dsl.compile(net, "torch").torch_compile is False
    assert tnn_dsl.TrainConfig(torch_compile=True).torch_compile is True


def test_cli_simulate_torch_compile_needs_the_torch_backend(tmp_path, capsys, monkeypatch):
    from tnn_dsl.cli import main

    compiled = []

    def fake_compile(fn, **kw):  # the flag's wiring, without paying for inductor (the model tests do that)
        compiled.append(fn)
        return fn

    monkeypatch.setattr(torch, "compile", fake_compile)

    thn = tmp_path / "rc.thn"
    thn.write_text("network rc\nunits temperature = degC\ninput P : [W]\nparam Ta = 20 degC\nboundary amb = Ta\n"
                   "node n  C = 100 J/K\nG n -- amb = 2 W/K\nsource n = P\nsensor Tn = n\n")
    csv = tmp_path / "d.csv"
    csv.write_text("t,P\n" + "".join(f"{k},{5.0 if k > 3 else 0.0}\n" for k in range(10)))
    rc = main(["simulate", str(thn), "--data", str(csv), "-o", str(tmp_path / "o.csv"), "--torch-compile"])
    err = capsys.readouterr().err
    assert rc != 0 and "--torch-compile applies to the torch backend only" in err and "Traceback" not in err
    out = tmp_path / "o2.csv"
    rc = main(["simulate", str(thn), "--data", str(csv), "-o", str(out), "--backend", "torch", "--torch-compile"])
    assert rc == 0 and compiled  # one graph per rollout kind (forward, chunked), each its own compile
    eager = tmp_path / "o3.csv"
    assert main(["simulate", str(thn), "--data", str(csv), "-o", str(eager), "--backend", "torch"]) == 0
    assert out.read_text() == eager.read_text()


@pytest.mark.parametrize("batched, with_grad", [(False, False), (True, False),
                                               pytest.param(False, True, marks=pytest.mark.slow),
                                               pytest.param(True, True, marks=pytest.mark.slow)])
def test_compiled_torch_with_many_substeps_matches_jax(batched, with_grad):
    """More than 4 sub-steps per sample: inside the compiled scan (forward) they are a scan of their own (not
    copies of the step); states (and, slow, gradients through the per-step compiled path) as JAX's
    ``fori_loop``, on a single sequence and on a batch."""
    net = tnn_dsl.loads(SMALL, "small.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 5)
    T0, U = _batch(mj, 9, B=2)
    if not batched:
        T0, U = T0[0], U[0]
    import jax
    import jax.numpy as jnp

    def jax_loss(p):
        _, y = mj.rollout(p, T0, U, 1.0, substeps=6)
        return jnp.sum(y * jnp.linspace(-1.0, 1.0, y.size).reshape(y.shape))

    pj = mj.from_numpy(p_np)
    s_ref = np.asarray(mj.rollout(pj, T0, U, 1.0, substeps=6)[0])
    g_ref = {k: np.asarray(v) for k, v in jax.grad(jax_loss)(pj).items()} if with_grad else {}
    pt = {k: v.requires_grad_(True) for k, v in mc.from_numpy(p_np).items()}
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        with torch.no_grad():
            s_fwd = mc.rollout(pt, torch.as_tensor(T0), torch.as_tensor(U), 1.0, substeps=6)[0]
        assert np.max(np.abs(s_fwd.numpy() - s_ref)) <= 1e-9
        if not with_grad:
            return
        s, y = mc.rollout(pt, torch.as_tensor(T0), torch.as_tensor(U), 1.0, substeps=6)
    (y * torch.linspace(-1.0, 1.0, y.numel(), dtype=y.dtype).reshape(y.shape)).sum().backward()
    assert np.max(np.abs(s.detach().numpy() - s_ref)) <= 1e-9
    scale = max(float(np.max(np.abs(g))) for g in g_ref.values() if g.size)
    for k, g in g_ref.items():
        got = np.zeros(g.shape) if pt[k].grad is None else pt[k].grad.numpy()
        tol = 1e-6 * max(float(np.max(np.abs(g), initial=0.0)), 1e-8 * scale)
        assert np.max(np.abs(got - g), initial=0.0) <= tol, k


def test_forward_mode_derivatives_run_eager_and_keep_compilation_on():
    """The burn-in fit of an initial state takes ``torch.func`` derivatives of a rollout; a compiled graph cannot be
    called inside one, so that rollout runs eager — without a warning and without turning compilation off for
    the rollouts after it (it used to: every later validation ran eager)."""
    net = nets.two_node()
    mc, me = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "torch")
    p = mc.init_params(0)
    U = torch.full((12, len(mc.input_names)), 2.0, dtype=torch.float64)
    T0 = torch.tensor([300.0, 296.0], dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        J = torch.func.jacfwd(lambda T: mc.rollout(p, T, U, 1.0)[1])(T0)
    J_eager = torch.func.jacfwd(lambda T: me.rollout(me.init_params(0), T, U, 1.0)[1])(T0)
    assert mc.torch_compile is True and torch.allclose(J, J_eager, rtol=0, atol=1e-12)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
@pytest.mark.parametrize("network", ["small", "tclab_lag"])
def test_burn_in_jacobian_by_central_differences_matches_forward_mode(network, compiled):
    """Torch fits the burn-in's initial state with central differences over one batched rollout, compiled or eager
    (forward mode runs eager either way, ~300 µs a step, and took 16 s an estimate on the case study's M2): the
    Jacobian agrees with JAX's ``jacfwd`` to 1e-6 relative on a network with an MLP and one with radiation."""
    from tnn_dsl.compiler import backend_of
    from tnn_dsl.fit.initial import _BurnInFit

    net = (tnn_dsl.loads(SMALL, "small.thn") if network == "small"
           else tnn_dsl.load(Path(__file__).resolve().parents[1] / "networks" / "tclab" / "tclab_lag.thn"))
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=compiled), tnn_dsl.compile(net, "jax")
    assert mc.torch_compile is compiled
    p_np = nets.random_params(mj, 2) if network == "small" else mj.to_numpy(mj.init_params(0))
    rng = np.random.default_rng(0)
    n, ni = 40, len(mj.input_names)
    U = rng.uniform(0.0, 100.0, (n, ni)) if network != "small" else _batch(mj, n, B=1)[1][0]  # heater % or case
    x = np.linspace(300.0, 310.0, len(mj.state_names))
    J = {}
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        for m in (mc, mj):
            B = backend_of(m)
            fit = _BurnInFit(m, 1.0, n, "rk4", None)
            args = (m.pack_params(m.from_numpy(p_np)), B.asarray(U), B.asarray(x))
            if B.name == "torch":  # one batched rollout of x and the perturbed states, not a tangent through every step
                assert fit.fJ is None and fit.fyJ.__qualname__.startswith("_central_difference_jacobian."), fit.fyJ
                y, J[B.name] = (B.numpy(a) for a in fit.fyJ(*args))
                np.testing.assert_allclose(y, B.numpy(fit.fy(*args)), rtol=0, atol=1e-9)  # the run from x, as alone
            else:  # forward mode: the readings and their Jacobian from one program
                assert fit.fJ is None, fit.fJ
                y, J[B.name] = (B.numpy(a) for a in fit.fyJ(*args))
                np.testing.assert_array_equal(y, B.numpy(fit.fy(*args)))
                alone = m.rollout(m.from_numpy(p_np), B.asarray(x), B.asarray(U), 1.0)[1]
                np.testing.assert_allclose(y, B.numpy(alone), rtol=0, atol=1e-12)
    assert J["torch"].shape == J["jax"].shape == (n, len(mj.output_names), len(mj.state_names))
    assert np.max(np.abs(J["torch"] - J["jax"])) <= 1e-6 * np.max(np.abs(J["jax"]))


@pytest.mark.slow
def test_gradient_rollout_in_compiled_chunks_matches_jax(monkeypatch):
    """``TORCH_GRAD_CHUNK`` > 1 (several steps per compiled graph with gradients; 3 here, so 11 intervals are
    padded to 12): the same states and gradients as JAX."""
    import tnn_dsl.compiler.model as compiled_model

    monkeypatch.setattr(compiled_model, "TORCH_GRAD_CHUNK", 3)
    monkeypatch.setattr(compiled_model, "TORCH_ADJOINT", False)
    net = tnn_dsl.loads(SMALL, "small.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 3)
    T0, U = _batch(mj, 12)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_run(mc, p_np, T0, U)
    assert any(k[0] == "torch_chunk" for k in mc._jit_cache if isinstance(k, tuple))
    _assert_same(_jax_run(mj, p_np, T0, U), got)


_TINY = """\
network tiny "one node and its loss to ambient: the smallest scan to compile"
units temperature = degC
input Ta : temperature
node a  C = 10 J/K
boundary amb = Ta
R a -- amb = 1 K/W
sensor T_a = a
"""

_VEC_PROBE = """
import sys, numpy as np, torch, tnn_dsl
from torch._inductor import cpu_vec_isa
net = tnn_dsl.loads(sys.stdin.read(), "tiny.thn")
m = tnn_dsl.compile(net, "torch", torch_compile=True)
p = m.init_params(seed=0)
with torch.no_grad():
    m.rollout(p, torch.full((len(m.state_names),), 300.0, dtype=torch.float64),
              torch.zeros((20, len(m.input_names)), dtype=torch.float64) + 300.0, 1.0)
assert any(isinstance(k, tuple) and k[0] in ("torch_scan", "torch_adjoint") for k in m._jit_cache), "no scan"
got = [str(i) for i in cpu_vec_isa.valid_vec_isa_list()]
cpu_vec_isa.valid_vec_isa_list.cache_clear()
print(got == [str(i) for i in cpu_vec_isa.valid_vec_isa_list()], got)
"""


def test_compiled_scans_leave_the_process_vectorisation_as_it_was(tmp_path):
    """The compiled scans are built without SIMD kernels (``cpp.vec_isa_ok = False``, the model's
    ``TORCH_VECTORIZE``), but torch 2.13 caches the machine's vector instruction sets per process under the first
    value it sees: in a fresh process, after a compiled scan, that list is the one a default compilation makes
    (else a user's own vectorised graph, loaded from inductor's on-disk cache, fails to build: 'at::vec' has not
    been declared)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=str(tmp_path / "inductor"))
    res = subprocess.run([sys.executable, "-c", _VEC_PROBE], input=_TINY, capture_output=True, text=True, env=env,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.startswith("True"), res.stdout
