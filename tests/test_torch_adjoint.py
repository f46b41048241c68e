"""Torch rollouts with gradients under ``torch_compile=True`` run as a compiled forward scan and a compiled adjoint
scan (:mod:`tnn_dsl.compiler.torch_adjoint`, issue 18): the same states and gradients (parameters, initial states,
inputs) as eager torch and as JAX on every network of the library and every integrator; the structure flattening
round-trips; a failing compiled backward warns and still gives exact gradients."""

from __future__ import annotations

import glob
import os
import warnings

import nets
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tnn_dsl
from tnn_dsl.compiler.assembly import _PackedVals, _Prep

torch = pytest.importorskip("torch")

from tnn_dsl.compiler.torch_adjoint import Unsupported, flatten  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NETWORKS = sorted(glob.glob(os.path.join(ROOT, "networks", "**", "*.thn"), recursive=True))
CHAIN = """\
network chain "two nodes, a learned conductance, a source on an input"
units temperature = degC
input P : [W]
input Ta : temperature
node a C = 100 J/K
node b C = 300 J/K
boundary amb = Ta
G a -- b = 2 W/K  as G_ab
R b -- amb = 0.8 K/W
source a = P
sensor T_a = a
learn G_ab as mlp(a, b; hidden = [3], activation = tanh)
"""
PLAIN_CHAIN = CHAIN.replace("learn G_ab as mlp(a, b; hidden = [3], activation = tanh)\n", "")
"""The chain without its learned conductance: for the tests of a mechanism whatever the step, whose scans compile in
half the time (the wrapper's fallback: 13.3 against 27.7 s alone, 2026-12-07)."""


def _inputs(model, N: int, B: int | None, seed: int = 0):
    """``T0`` K and inputs for ``model``: temperatures near 295 K, other inputs in [0, 1] (SI), random."""
    rng = np.random.default_rng(seed)
    net = model.network
    temp = {i.name for i in net.inputs if i.is_temperature}
    shape = (N,) if B is None else (B, N)
    U = np.stack([(290.0 + 10 * rng.random(shape)) if name in temp else rng.random(shape)
                  for name in model.input_names], -1)
    n = len(model.state_names)
    T0 = 296.0 + rng.random(n if B is None else (B, n))
    return T0, U


def _torch_grads(model, p_np, T0, U, integrator="rk4", substeps=None):
    p = {k: v.requires_grad_(True) for k, v in model.from_numpy(p_np).items() if v.dtype.is_floating_point}
    T0t = torch.as_tensor(T0).requires_grad_(True)
    Ut = torch.as_tensor(U).requires_grad_(True)
    s, y = model.rollout({**model.from_numpy(p_np), **p}, T0t, Ut, 1.0, integrator=integrator, substeps=substeps)
    ws = torch.linspace(-1.0, 1.0, s.numel(), dtype=s.dtype).reshape(s.shape)
    wy = torch.linspace(0.5, -0.5, y.numel(), dtype=y.dtype).reshape(y.shape)
    ((s * ws).sum() + (y * wy).sum()).backward()
    out = {"states": s.detach().numpy(), "T0'": T0t.grad.numpy(), "U'": Ut.grad.numpy()}
    out.update({k: (np.zeros(v.shape) if v.grad is None else v.grad.numpy()) for k, v in p.items()})
    return out


def _jax_grads(model, p_np, T0, U, integrator="rk4", substeps=None):
    import jax
    import jax.numpy as jnp

    def loss(p, T0, U):
        s, y = model.rollout(p, T0, U, 1.0, integrator=integrator, substeps=substeps)
        ws = jnp.linspace(-1.0, 1.0, s.size).reshape(s.shape)
        wy = jnp.linspace(0.5, -0.5, y.size).reshape(y.shape)
        return (s * ws).sum() + (y * wy).sum()

    p = model.from_numpy(p_np)
    gp, gT, gU = jax.grad(loss, argnums=(0, 1, 2))(p, jnp.asarray(T0), jnp.asarray(U))
    out = {"states": np.asarray(model.rollout(p, T0, U, 1.0, integrator=integrator, substeps=substeps)[0]),
           "T0'": np.asarray(gT), "U'": np.asarray(gU)}
    out.update({k: np.asarray(v) for k, v in gp.items()})
    return out


def _assert_close(ref, got, *, atol=1e-9, rtol=1e-6):
    assert np.max(np.abs(ref["states"] - got["states"])) <= atol
    scale = max(float(np.max(np.abs(v))) for k, v in ref.items() if k != "states" and v.size)
    for k, v in ref.items():
        if k != "states" and v.size and k in got:
            tol = rtol * max(float(np.max(np.abs(v))), 1e-8 * scale)
            assert np.max(np.abs(v - got[k])) <= tol, (k, float(np.max(np.abs(v - got[k]))), tol)


def _adjoint_used(model) -> bool:
    return any(isinstance(k, tuple) and k[0] == "torch_adjoint" for k in model._jit_cache)


# one sequence is slow here (24 s in CI, 2026-12-04): the batched variant runs single sequences without gradients
# through the compiled forward, and the float32 test below differentiates a single sequence
@pytest.mark.parametrize("batch", [3, pytest.param(None, marks=pytest.mark.slow)], ids=["batch", "single"])
def test_adjoint_matches_eager_and_jax(batch):
    """States and gradients as eager torch's and JAX's. With a batch (issue 18), the rollouts without gradients
    after it (a training's validation free run, its burn-in's batched Jacobian, a free run after the training) run
    through the forward scan the rollouts with gradients compiled, whatever their batch (one sequence runs as two)
    and length: no graph of their own (the case study's M2 compiled four graphs per training, two of them for its
    validation), JAX's states to 1e-9 K."""
    from torch._dynamo.utils import counters

    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, me, mj = (tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "torch"),
                  tnn_dsl.compile(net, "jax"))
    p_np = nets.random_params(mj, 2)
    T0, U = _inputs(mj, 9, batch)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U)
        assert _adjoint_used(mc)
        graphs = counters["stats"]["unique_graphs"]
        # a second window length reuses the compiled programs (the scan's length is dynamic) and is still exact
        T0b, Ub = _inputs(mj, 5, batch, seed=1)
        got_b = _torch_grads(mc, p_np, T0b, Ub)
        if batch is not None:
            T1, U1 = _inputs(mj, 23, 4, seed=3)
            for T0_, U_ in ((T1[0], U1[0]), (T1, U1), (T1[:2], U1[:2, :11])):
                with torch.no_grad():
                    s = mc.rollout(mc.from_numpy(p_np), torch.as_tensor(T0_), torch.as_tensor(U_), 1.0)[0]
                ref = np.asarray(mj.rollout(mj.from_numpy(p_np), T0_, U_, 1.0)[0])
                assert s.shape == ref.shape and np.max(np.abs(s.numpy() - ref)) <= 1e-9
            runner = next(v for v in mc._jit_cache.values() if hasattr(v, "_fwd"))
            assert len(runner._fwd) == 1 and not any(k[0] == "torch_scan" for k in mc._jit_cache if type(k) is tuple)
    assert counters["stats"]["unique_graphs"] == graphs
    _assert_close(_torch_grads(me, p_np, T0, U), got)
    _assert_close(_jax_grads(mj, p_np, T0, U), got)
    _assert_close(_jax_grads(mj, p_np, T0b, Ub), got_b)


def test_a_helper_shares_the_compilation_through_hooks_around_the_first_reverse_call(monkeypatch):
    """:data:`~tnn_dsl.compiler.torch_adjoint.SHARED` (the helper that compiles a training's reverse scan beside it,
    ``tnn_dsl.fit.compile_ahead.CompileBeside``): ``before_backward`` and ``after_backward`` are called around the
    call that compiles a reverse scan and not around the later calls of that program (another window length), and
    the helper's uncompiled forward gives the compiled forward's states and, through the same reverse program, its
    gradients."""
    from tnn_dsl.compiler import torch_adjoint as ta

    calls: list[str] = []
    monkeypatch.setattr(ta.SHARED, "before_backward", lambda: calls.append("before"))
    monkeypatch.setattr(ta.SHARED, "after_backward", lambda: calls.append("after"))
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc = tnn_dsl.compile(net, "torch", torch_compile=True)
    p_np = nets.random_params(tnn_dsl.compile(net, "jax"), 2)
    T0, U = _inputs(mc, 9, 3)
    compiled = _torch_grads(mc, p_np, T0, U)
    assert _adjoint_used(mc) and calls == ["before", "after"]
    T0b, Ub = _inputs(mc, 5, 3, seed=1)
    _torch_grads(mc, p_np, T0b, Ub)
    assert calls == ["before", "after"]  # the program compiled: no hook
    monkeypatch.setattr(ta.SHARED, "eager_forward", True)
    eager = _torch_grads(mc, p_np, T0, U)
    assert calls == ["before", "after"]
    _assert_close(compiled, eager, atol=1e-9, rtol=1e-9)


def _n_tensors(spec) -> int:
    """The tensors :func:`flatten`'s key describes."""
    if type(spec) is not tuple or not spec:
        return 0
    if spec[0] == "T" and len(spec) == 4:
        return 1
    return sum(_n_tensors(x) for x in spec)


def test_the_reverse_scan_differentiates_only_what_autograd_asks_for():
    """Of a training's prepared tensors most are constants and its inputs need no gradient: the reverse scan
    differentiates only the tensors autograd asks for (issue 18: M2's 5 of 43, which took its backward pass from
    35 to 26 ms), and their gradients are still JAX's to 1e-6 relative; the inputs' and the initial state's are not
    computed at all. A later call that wants every gradient compiles a reverse graph of its own and gets them all."""
    import jax
    import jax.numpy as jnp

    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 4)
    T0, U = _inputs(mj, 7, 3)
    wanted = sorted(k for k in p_np if k.startswith("fn_"))  # the learned conductance's weights only
    assert wanted and len(wanted) < len(p_np)
    p = mc.from_numpy(p_np)
    for k in wanted:
        p[k] = p[k].requires_grad_(True)
    T0t, Ut = torch.as_tensor(T0), torch.as_tensor(U)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        s = mc.rollout(p, T0t, Ut, 1.0)[0]
        (s * torch.linspace(-1.0, 1.0, s.numel(), dtype=s.dtype).reshape(s.shape)).sum().backward()
    assert _adjoint_used(mc)
    runner = next(v for v in mc._jit_cache.values() if hasattr(v, "_bwd"))
    (key, ip, ic), = runner._bwd
    ckeys = key[1]
    assert 0 < len(ip) < _n_tensors(key[0])  # some prepared tensors, not all
    assert ckeys.index(("u", None)) not in ic and len(ic) < len(ckeys)  # the inputs' gradient is not computed

    def loss(pw):
        s = mj.rollout({**mj.from_numpy(p_np), **pw}, jnp.asarray(T0), jnp.asarray(U), 1.0)[0]
        return (s * jnp.linspace(-1.0, 1.0, s.size).reshape(s.shape)).sum()

    ref = jax.grad(loss)({k: jnp.asarray(p_np[k]) for k in wanted})
    for k in wanted:
        r = np.asarray(ref[k])
        assert np.max(np.abs(p[k].grad.numpy() - r)) <= 1e-6 * max(float(np.max(np.abs(r))), 1e-12), k
    # every gradient wanted: a reverse graph of its own, differentiating more
    got = _torch_grads(mc, p_np, T0, U)
    assert len(runner._bwd) == 2
    assert max(len(k[1]) for k in runner._bwd) > len(ip) and max(len(k[2]) for k in runner._bwd) > 0
    _assert_close(_jax_grads(mj, p_np, T0, U), got)


@pytest.mark.slow  # the fast suite's compiled-torch tests cover RK4; the slow case-study test covers expeuler too
@pytest.mark.parametrize("integrator,substeps", [("expeuler", None), ("euler", 6)])
def test_adjoint_other_integrators(integrator, substeps):
    """Exponential Euler (the diagonal part in closed form) and more than 4 sub-steps (a nested ``scan`` in the
    compiled forward; a Python loop of sub-steps in the traced vector-Jacobian product)."""
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 4)
    T0, U = _inputs(mj, 6, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U, integrator, substeps)
    _assert_close(_jax_grads(mj, p_np, T0, U, integrator, substeps), got)


def _compile_failing_when(fails, message: str):
    """A stand-in for ``torch.compile``: the graphs for which ``fails(fn, kwargs)`` holds raise
    ``RuntimeError(message)`` when called (as a compilation failing on the first call does); the rest compile."""
    real = torch.compile

    def fake(fn, **kw):
        if fails(fn, kw):
            def call(*a, **k):
                raise RuntimeError(message)
            return call
        return real(fn, **kw)
    return fake


def test_failing_compiled_backward_warns_and_stays_exact(monkeypatch):
    """If inductor cannot compile the adjoint scan, the gradients come from the traced step run uncompiled, after
    one warning; the forward stays compiled."""
    backward = _compile_failing_when(lambda fn, kw: fn.__name__.startswith("tnn_adjoint_bwd"),
                                     "no C++ compiler for this one")
    monkeypatch.setattr(torch, "compile", backward)
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, me = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(me, 1)
    T0, U = _inputs(me, 7, 2)
    with pytest.warns(tnn_dsl.TorchCompileWarning, match="backward pass.*no C.. compiler"):
        got = _torch_grads(mc, p_np, T0, U)
    assert mc.torch_compile is True and _adjoint_used(mc)
    _assert_close(_torch_grads(me, p_np, T0, U), got)


def test_cpp_wrapper_failure_falls_back_to_the_python_wrapper(monkeypatch):
    """When inductor's C++ wrapper cannot build a scan (torch 2.13 declares a buffer twice in some reverse scans),
    the scan is compiled again with the Python wrapper, without a warning: forward and backward stay compiled and
    exact, and the scan records why (``fallback``)."""
    from tnn_dsl.compiler.torch_adjoint import CompiledScan

    seen: list[tuple[str, bool]] = []

    def cpp(fn, kw) -> bool:
        seen.append((fn.__name__, bool((kw.get("options") or {}).get("cpp_wrapper"))))
        return seen[-1][1]

    monkeypatch.setattr(torch, "compile", _compile_failing_when(cpp, "conflicting declaration 'auto buf35'"))
    net = tnn_dsl.loads(PLAIN_CHAIN, "chain.thn")
    assert not net.learned
    mc, me = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "torch")
    p_np = nets.random_params(me, 2)
    T0, U = _inputs(me, 7, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U)
    assert mc.torch_compile is True and _adjoint_used(mc)
    _assert_close(_torch_grads(me, p_np, T0, U), got)
    runner = next(v for v in mc._jit_cache.values() if hasattr(v, "_bwd"))
    scans = [*runner._fwd.values(), *(entry[1] for entry in runner._bwd.values())]  # (graph, scan, 0-d slots)
    assert len(scans) == 2 and all(isinstance(f, CompiledScan) and "buf35" in f.fallback for f in scans)
    adjoint = [(n, cpp) for n, cpp in seen if n.startswith("tnn_adjoint_")]
    assert [cpp for _, cpp in adjoint] == [True, False, True, False]  # each scan: C++ tried, then Python
    assert all(n.endswith("_py") for n, cpp in adjoint if not cpp)

    def always_fails(fn, **kw):
        def call(*a, **k):
            raise RuntimeError("no C++ compiler")
        return call

    monkeypatch.setattr(torch, "compile", always_fails)  # the Python wrapper failing too is the caller's to handle
    scan = CompiledScan(lambda x: x, "tnn_test_scan", {"cpp_wrapper": True})
    with pytest.raises(RuntimeError, match="no C"):
        scan(torch.ones(1))
    assert scan.fallback is not None


def _example_prep():
    p = _Prep()
    p.vals = {"a": torch.ones(2, requires_grad=True), "b": 3, "c": None}
    p.arrays = {"fn": {"W0": torch.zeros(2, 3), "b0": torch.zeros(3, dtype=torch.float32)}}
    p.scales = [torch.tensor(1.0), (torch.arange(3), "x")]
    p.z = {}
    return p


def test_flatten_round_trips_and_keys_say_what_can_share_code():
    p = _example_prep()
    ts, rebuild, key = flatten(p)
    assert len(ts) == 5
    new = [t.detach() + 1 if t.dtype.is_floating_point else t for t in ts]
    q = rebuild(new)
    assert isinstance(q, _Prep) and q.vals["b"] == 3 and q.vals["c"] is None and q.scales[1][1] == "x"
    assert torch.equal(q.vals["a"], ts[0].detach() + 1) and q.arrays["fn"]["b0"].dtype == torch.float32
    assert isinstance(q.scales, list) and isinstance(q.scales[1], tuple)
    assert flatten(_example_prep())[2] == key
    other = _example_prep()
    other.vals["a"] = torch.ones(3, requires_grad=True)
    assert flatten(other)[2] != key
    other = _example_prep()
    other.vals["b"] = 4
    assert flatten(other)[2] != key
    packed = _Prep()
    packed.vals = _PackedVals(torch.zeros(4), {"x": 0})
    with pytest.raises(Unsupported):
        flatten(packed)


@settings(max_examples=60, deadline=None)
@given(st.recursive(st.one_of(st.none(), st.integers(-3, 3), st.text(max_size=3),
                              st.lists(st.integers(1, 3), min_size=0, max_size=2).map(lambda s: ("shape", tuple(s)))),
                    lambda kids: st.one_of(st.lists(kids, max_size=3), st.tuples(kids, kids),
                                           st.dictionaries(st.text(max_size=2), kids, max_size=3)),
                    max_leaves=12))
def test_flatten_round_trip_property(tree):
    def realise(o):
        if isinstance(o, tuple) and len(o) == 2 and o[0] == "shape":
            return torch.randn(o[1], dtype=torch.float64)
        if isinstance(o, list):
            return [realise(v) for v in o]
        if isinstance(o, tuple):
            return tuple(realise(v) for v in o)
        if isinstance(o, dict):
            return {k: realise(v) for k, v in o.items()}
        return o

    t = realise(tree)
    ts, rebuild, key = flatten(t)
    back = rebuild(ts)
    ts2, _, key2 = flatten(back)
    assert key2 == key and len(ts2) == len(ts) and all(a is b for a, b in zip(ts, ts2))


@pytest.mark.slow
@pytest.mark.parametrize("path", NETWORKS, ids=lambda p: os.path.relpath(p, os.path.join(ROOT, "networks")))
def test_adjoint_matches_jax_on_every_network(path):
    """Issue 18's exactness: ≤ 1e-9 K and gradients ≤ 1e-6 relative to JAX, every network of ``networks/``; the
    forward scan (no gradient) too, batched and on one sequence (M4's learned Peltier fell back to eager there)."""
    net = tnn_dsl.load(path)
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    if mc.sparse:
        pytest.skip("large networks take the step-by-step path (packed parameter table)")
    p_np = nets.random_params(mj, 0)
    T0, U = _inputs(mj, 8, 2)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U)
    assert _adjoint_used(mc)
    _assert_close(_jax_grads(mj, p_np, T0, U), got)
    nets.assert_compiled_forward_matches_jax(mc, mj, p_np, T0, U)


def test_adjoint_float32_two_samples_and_no_second_derivative():
    """A float32 model over the shortest rollout the compiled reverse scan runs (two sequences of three samples, two
    steps; one step runs a Python loop of the traced step, the next test): the gradient is as accurate as eager
    torch's in float32 — both within float32 round-off of the float64 gradient at the same (float32) values; a
    backward pass that would build a graph for second derivatives raises (they would miss the rollout's part)
    instead of giving a silently partial answer.

    The reference is float64, not eager float32: the two float32 computations sum in different orders, and a small
    gradient that is a sum of large terms carries an error of order ``eps32 × the largest gradient`` in either
    (measured 2026-11-27: ``R_b_amb``'s, 5.7e-4, is off by 8.3e-8 eager and 1.0e-8 compiled, so eager against
    compiled missed a 1e-4 relative bound)."""
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc = tnn_dsl.compile(net, "torch", dtype="float32", torch_compile=True)
    me = tnn_dsl.compile(net, "torch", dtype="float32")
    p_np = {k: np.asarray(v, np.float32).astype(np.float64)
            for k, v in nets.random_params(tnn_dsl.compile(net, "numpy"), 5).items()}
    T0, U = _inputs(me, 3, 2)
    T0, U = T0.astype(np.float32), U.astype(np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U)
    assert _adjoint_used(mc)
    exact = _torch_grads(tnn_dsl.compile(net, "torch"), p_np, T0.astype(np.float64), U.astype(np.float64))
    eager = _torch_grads(me, p_np, T0, U)
    scale = max(float(np.max(np.abs(v))) for k, v in exact.items() if k != "states" and v.size)
    for k, v in exact.items():
        if not v.size:
            continue
        # float32 round-off: 1e-3 K on the states; a gradient within 1e-4 of itself plus 4 eps32 times the largest
        tol = 1e-3 if k == "states" else (1e-4 * float(np.max(np.abs(v)))
                                          + 4 * float(np.finfo(np.float32).eps) * scale)
        for name, res in (("compiled", got), ("eager", eager)):
            err = float(np.max(np.abs(res[k] - v)))
            assert err <= tol, (name, k, err, tol)
    p = {k: v.requires_grad_(True) for k, v in mc.from_numpy(p_np).items()}
    s, _ = mc.rollout(p, torch.as_tensor(T0), torch.as_tensor(U), 1.0)
    with pytest.raises(NotImplementedError, match="second derivatives.*torch_compile=False"):
        torch.autograd.grad(s.sum(), [p["fn_G_ab.W0"]], create_graph=True)


def test_one_step_of_one_sequence_has_exact_gradients():
    """A rollout of two samples (one step) of a single sequence: JAX's gradients to 1e-6 relative. torch 2.13's
    compiled reverse scan of length one on a batch of one added a context array's gradient to a 0-d parameter's
    (the chain's ``R_b_amb`` off by 17 %, 2026-12-04); one step now runs the traced step once, uncompiled."""
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 5)
    T0, U = _inputs(mj, 2, None)
    with warnings.catch_warnings():
        warnings.simplefilter("error", tnn_dsl.TorchCompileWarning)
        got = _torch_grads(mc, p_np, T0, U)
    assert _adjoint_used(mc)
    _assert_close(_jax_grads(mj, p_np, T0, U), got)


@pytest.mark.parametrize("lead", [(), (5,), (4, 3)], ids=["vector", "batch", "two batch axes"])
def test_small_products_are_batch_last_and_equal_matmul(lead):
    """The compiled scans' product of vectors by a small matrix (``FusedTorchXP.matmul``) equals ``torch.matmul``
    to round-off for one vector and for any leading batch axes, and a batch comes back with the batch axis
    contiguous (stride 1): inductor lays what follows out that way and its SIMD kernels run along the windows
    (issue 18)."""
    from tnn_dsl.compiler.backends.torch_ops import SMALL_MATMUL, fused_matmul

    g = torch.Generator().manual_seed(0)
    a = torch.randn(*lead, 6, generator=g, dtype=torch.float64)
    for n_out in (1, 8, SMALL_MATMUL // 6):
        b = torch.randn(6, n_out, generator=g, dtype=torch.float64)
        got = fused_matmul(a, b)
        ref = torch.matmul(a, b)
        assert got.shape == ref.shape
        assert torch.max(torch.abs(got - ref)) <= 1e-13 * max(1.0, float(torch.max(torch.abs(ref))))
        if lead:
            assert got.stride(-2) == 1, got.stride()
    big = torch.randn(6, SMALL_MATMUL, generator=g, dtype=torch.float64)  # past the limit: torch.matmul itself
    assert torch.equal(fused_matmul(a, big), torch.matmul(a, big))


@pytest.mark.slow  # SIMD kernels compile for a minute; the fast suite's batch-last test checks the product
@pytest.mark.parametrize("how", ["environment", "batch size"])
def test_simd_kernels_match_jax(monkeypatch, how):
    """With inductor's SIMD kernels (``TNN_TORCH_SIMD=1``, or by default for a rollout of ``TORCH_SIMD_MIN_BATCH``
    sequences and ``TORCH_SIMD_MIN_WINDOW_STEPS`` samples; ``TORCH_SIMD_BITS`` wide) a batch's states and
    gradients are JAX's (1e-9 K, 1e-6 relative); a free run of two sequences after it runs on the same compiled
    forward scan."""
    import tnn_dsl.compiler.model as compiled_model

    if how == "environment":
        monkeypatch.setenv("TNN_TORCH_SIMD", "1")
    else:
        monkeypatch.delenv("TNN_TORCH_SIMD", raising=False)
        monkeypatch.setattr(compiled_model, "TORCH_VECTORIZE", False)
        monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_BATCH", 16)
        monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_WINDOW_STEPS", 16 * 8)
    net = tnn_dsl.loads(CHAIN, "chain.thn")
    mc, mj = tnn_dsl.compile(net, "torch", torch_compile=True), tnn_dsl.compile(net, "jax")
    p_np = nets.random_params(mj, 2)
    T0, U = _inputs(mj, 9, 16)
    got = _torch_grads(mc, p_np, T0, U)
    assert _adjoint_used(mc)
    assert [k[6] for k in mc._jit_cache if type(k) is tuple and k[0] == "torch_adjoint"] == [True]
    _assert_close(_jax_grads(mj, p_np, T0, U), got)
    with torch.no_grad():
        s = mc.rollout(mc.from_numpy(p_np), torch.as_tensor(T0[:2]), torch.as_tensor(U[:2]), 1.0)[0]
    assert np.max(np.abs(s.numpy() - np.asarray(mj.rollout(mj.from_numpy(p_np), T0[:2], U[:2], 1.0)[0]))) <= 1e-9
    assert [k[6] for k in mc._jit_cache if type(k) is tuple and k[0] == "torch_adjoint"] == [True]


def test_large_batches_get_simd_kernels_and_free_runs_reuse_a_compiled_scan(monkeypatch):
    """By default (``TORCH_VECTORIZE`` off, ``TNN_TORCH_SIMD`` unset) a rollout with gradients of a network with an
    MLP of a smooth activation, of at least ``TORCH_SIMD_MIN_BATCH`` sequences and ``TORCH_SIMD_MIN_WINDOW_STEPS``
    samples in all, gets SIMD kernels, others scalar kernels; a free run (no gradients) takes whichever runner the
    model already has rather than compiling another (scalar where it has none), unless the environment chooses.
    Nothing is compiled here: the runners compile at their first call."""
    import tnn_dsl.compiler.model as compiled_model
    from tnn_dsl.compiler.model import _torch_vectorize

    monkeypatch.setattr(compiled_model, "TORCH_VECTORIZE", False)
    monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_BATCH", 16)
    monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_WINDOW_STEPS", 65_536)
    monkeypatch.delenv("TNN_TORCH_SIMD", raising=False)
    sizes = [(None, None), (256, None), (1, 10**6), (15, 10**5), (16, 4096), (24, 600), (256, 390), (16, 4095)]
    assert [_torch_vectorize(b, n, True) for b, n in sizes] == [False, False, False, False, True, False, True, False]
    assert not _torch_vectorize(256, 390, False)  # no MLP: nothing to vectorise that the scalar kernels do not
    monkeypatch.setenv("TNN_TORCH_SIMD", "0")
    assert not _torch_vectorize(256, 390, True)
    monkeypatch.setenv("TNN_TORCH_SIMD", "1")
    assert _torch_vectorize(1, 1) and _torch_vectorize()
    monkeypatch.delenv("TNN_TORCH_SIMD")
    monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_WINDOW_STEPS", None)
    assert not _torch_vectorize(256, 10**6, True)
    monkeypatch.setattr(compiled_model, "TORCH_SIMD_MIN_WINDOW_STEPS", 65_536)
    for learn, simd in (("mlp(a, b; hidden = [3], activation = relu)", False), ("linear(a, b)", False),
                        ("mlp(a, b; hidden = [3], activation = sigmoid)", True)):
        other = tnn_dsl.compile(tnn_dsl.loads(CHAIN.replace("mlp(a, b; hidden = [3], activation = tanh)", learn),
                                              "chain.thn"), "torch", torch_compile=True)
        runner = other._adjoint_runner(1.0, "rk4", None, False, batch=256, samples=390)
        assert ("cpp.vec_isa_ok" not in runner.options) is simd, learn

    mc = tnn_dsl.compile(tnn_dsl.loads(CHAIN, "chain.thn"), "torch", torch_compile=True)
    big = mc._adjoint_runner(1.0, "rk4", None, False, batch=256, samples=390)
    assert "cpp.vec_isa_ok" not in big.options
    assert mc._adjoint_runner(1.0, "rk4", None, False, reuse=True) is big  # a free run after it: no new graph
    small = mc._adjoint_runner(1.0, "rk4", None, False, batch=24, samples=600)  # the case study's training
    assert small is not big and small.options.get("cpp.vec_isa_ok") is False
    assert mc._adjoint_runner(1.0, "rk4", None, False, reuse=True) is small
    alone = tnn_dsl.compile(tnn_dsl.loads(CHAIN, "chain.thn"), "torch", torch_compile=True)  # a free run first
    assert alone._adjoint_runner(1.0, "rk4", None, False, reuse=True).options.get("cpp.vec_isa_ok") is False
    assert mc._adjoint_runner(1.0, "rk4", None, True, batch=1, samples=10**6).options.get("cpp.vec_isa_ok") is False
    fresh = tnn_dsl.compile(tnn_dsl.loads(CHAIN, "chain.thn"), "torch", torch_compile=True)
    simd_only = fresh._adjoint_runner(1.0, "rk4", None, False, batch=256, samples=390)
    monkeypatch.setenv("TNN_TORCH_SIMD", "0")  # the user's choice wins over reuse
    assert fresh._adjoint_runner(1.0, "rk4", None, False, reuse=True) is not simd_only


def test_simd_kernels_follow_the_environment(monkeypatch):
    """``TNN_TORCH_SIMD=1`` turns the compiled scans' SIMD kernels on (no ``cpp.vec_isa_ok = False`` in inductor's
    options), ``0`` or unset leaves the module's default, and a malformed value is a clear error when the model is
    compiled, not a traceback at its first rollout."""
    import tnn_dsl.compiler.model as compiled_model

    monkeypatch.setattr(compiled_model, "TORCH_VECTORIZE", False)
    monkeypatch.delenv("TNN_TORCH_SIMD", raising=False)
    assert compiled_model.inductor_options().get("cpp.vec_isa_ok") is False
    monkeypatch.setenv("TNN_TORCH_SIMD", "1")
    opts = compiled_model.inductor_options()
    assert "cpp.vec_isa_ok" not in opts
    monkeypatch.setenv("TNN_TORCH_SIMD", "0")
    monkeypatch.setattr(compiled_model, "TORCH_VECTORIZE", True)
    assert compiled_model.inductor_options().get("cpp.vec_isa_ok") is False
    monkeypatch.setenv("TNN_TORCH_SIMD", "yes")
    with pytest.raises(tnn_dsl.TnnError, match="TNN_TORCH_SIMD must be 0 or 1"):
        tnn_dsl.compile(tnn_dsl.loads(CHAIN, "chain.thn"), "torch", torch_compile=True)
