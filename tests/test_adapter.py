"""The backend adapter (tnn_dsl/compiler/backends/adapter.py) and the compiled-model protocol: every
transform gives the same numbers on JAX and torch, and agrees with finite differences."""

from __future__ import annotations

import os

import numpy as np
import pytest

from tnn_dsl.compiler.backends.adapter import Backend, backend_of
from tnn_dsl.compiler.protocol import CompiledModel

BACKENDS = ["jax", "torch"]
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
A = np.array([[1.0, 2.0, 0.5], [0.3, -1.0, 4.0]])


def _f(B):
    """f(x) = tanh(A x) · exp(x0), R³ → R² (written once against the adapter's namespace)."""
    a = B.asarray(A)

    def f(x):
        return B.xp.tanh(a @ x) * B.xp.exp(x[0])

    return f


def _jac_fd(x, h=1e-6):
    def f(x):
        return np.tanh(A @ x) * np.exp(x[0])

    return np.stack([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(3)], axis=-1)


@pytest.mark.parametrize("backend", BACKENDS)
def test_conversions_keep_shapes_and_kinds(backend):
    B = Backend(backend)
    assert tuple(B.asarray(np.asarray(3.0)).shape) == ()
    assert B.numpy(B.asarray(np.arange(6.0).reshape(2, 3).T)).tolist() == np.arange(6.0).reshape(2, 3).T.tolist()
    idx = B.asarray(np.array([0, 2]))
    assert "int" in str(idx.dtype)
    t = B.tree({"a": [1.0, np.ones(2)], "b": np.zeros((2, 2))})
    assert B.numpy(t["a"][1]).shape == (2,) and B.numpy(t["b"]).shape == (2, 2)
    assert Backend(backend, "float32").asarray(np.ones(2)).dtype == Backend(backend, "float32").dtype
    with pytest.raises(ValueError, match="no autodiff backend 'tensorflow'"):
        Backend("tensorflow")


def test_numpy_adapter_simulates_and_refuses_derivatives():
    """``Backend("numpy")`` (the reference backend, for simulations): conversions in its dtype, a Python-loop scan,
    and a clear error for every derivative instead of a torch or JAX path."""
    B = Backend("numpy", "float32")
    x = B.asarray([1.0, 2.0])
    assert isinstance(x, np.ndarray) and x.dtype == np.float32
    assert B.asarray(np.array([0, 2])).dtype.kind == "i"
    assert B.jit(np.sin) is np.sin and B.no_grad(np.sin)(0.0) == 0.0
    carry, ys = B.scan(lambda c, x: (c + x[0], 2 * c), 0.0, (np.arange(4.0),))
    assert carry == 6.0 and ys.tolist() == [0.0, 0.0, 2.0, 6.0]
    assert float(B.amax(np.array([[1.0, 3.0]]), (0, 1))) == 3.0 and B.clip_min(np.array([-1.0]), 0.0).tolist() == [0.0]
    np.testing.assert_allclose(B.sigmoid(np.array([0.3])), 1 / (1 + np.exp(-0.3)), rtol=1e-14)
    for call in (lambda: B.value_and_grad(np.sum), lambda: B.jvp(np.sin, (x,), (x,)),
                 lambda: B.jacobian(np.sin, [0.0]), lambda: B.jacobian_fn(np.sin, 1),
                 lambda: B.batched_jvp(np.sin, (x,), (x[None],))):
        with pytest.raises(NotImplementedError, match="numpy reference backend has no autodiff"):
            call()


@pytest.mark.parametrize("backend", BACKENDS)
def test_derivatives_match_finite_differences(backend):
    B = Backend(backend)
    f = _f(B)
    x = np.array([0.2, -0.4, 0.7])
    J = _jac_fd(x)
    np.testing.assert_allclose(B.jacobian(f, x), J, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(B.numpy(B.jacobian_fn(lambda x: f(x), 2, batched=False)(B.asarray(x))), J, rtol=1e-7)
    v = np.array([1.0, 0.5, -2.0])
    y, jv = B.jvp(f, (B.asarray(x),), (B.asarray(v),))
    np.testing.assert_allclose(B.numpy(jv), J @ v, rtol=1e-7)
    V = np.eye(3)
    np.testing.assert_allclose(B.numpy(B.batched_jvp(f, (B.asarray(x),), (B.asarray(V),))), (J @ V).T, rtol=1e-7)

    def loss(z, w):
        return B.sum(f(z) ** 2) * w

    val, grad = B.value_and_grad(loss)(x, 2.0)
    np.testing.assert_allclose(val, 2.0 * np.sum((np.tanh(A @ x) * np.exp(x[0])) ** 2))
    np.testing.assert_allclose(grad, 2.0 * 2.0 * J.T @ (np.tanh(A @ x) * np.exp(x[0])), rtol=1e-7)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_jacobian_rows_and_scan(backend):
    B = Backend(backend)
    a = B.asarray(A)

    def g(x):  # accepts a leading batch axis
        return B.xp.tanh(x @ a.T) * B.xp.exp(x[..., :1])

    x = np.array([0.2, -0.4, 0.7])
    np.testing.assert_allclose(B.numpy(B.jacobian_fn(g, 2, batched=True)(B.asarray(x))), _jac_fd(x), rtol=1e-7)

    def body(c, xs):
        (u,) = xs
        c = 0.5 * c + u
        return c, (c, 2 * c)

    c, (ys, zs) = B.scan(body, B.asarray(0.0), (B.asarray(np.arange(4.0)),))
    assert B.numpy(ys).tolist() == [0.0, 1.0, 2.5, 4.25] and B.numpy(zs).tolist() == [0.0, 2.0, 5.0, 8.5]
    assert float(B.numpy(c)) == 4.25


@pytest.mark.parametrize("backend", BACKENDS)
def test_jit_fallback_runs_untraceable_functions(backend):
    B = Backend(backend)

    def branchy(x):
        return x * 2 if float(B.numpy(x).sum()) > 0 else -x

    f = B.jit(branchy, fallback=True)
    assert B.numpy(f(B.asarray(np.ones(2)))).tolist() == [2.0, 2.0]
    assert B.numpy(f(B.asarray(-np.ones(2)))).tolist() == [1.0, 1.0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_compiled_models_satisfy_the_protocol(backend):
    import tnn_dsl
    from tnn_dsl.studies.casestudy import network_path

    net = tnn_dsl.load(network_path("tclab/tclab.thn"))
    model = tnn_dsl.compile(net, backend=backend)
    assert isinstance(model, CompiledModel)
    assert backend_of(model).name == backend


@pytest.mark.parametrize("backend", BACKENDS)
def test_lean_programs_give_the_default_programs_numbers(backend):
    """``jit(..., lean=True)`` (XLA's loop emitters on a CPU, issue 18) changes how a program is compiled, not what it
    computes: case-study M3's rollout (an MLP heat pipe, RK4) and its forward-mode Jacobian agree with the default
    program's to round-off, and the installed XLA knows the lean options (else they would be silently dropped).
    Torch has no lean programs: its ``jit`` hands back the function itself, lean or not, so the torch variant checks
    that instead of running the same eager function twice (18.6 s in CI for a comparison that could not fail)."""
    from conftest import FUSED_XLA_OPTIONS

    import tnn_dsl
    from tnn_dsl.compiler.backends.adapter import _lean_options_accepted
    from tnn_dsl.studies.casestudy import network_path

    model = tnn_dsl.compile(tnn_dsl.load(network_path("peltier_heatpipe/m3.thn")), backend=backend)
    B = backend_of(model)
    if backend == "torch":
        f = model.rollout
        assert B.lean_options() is None
        assert B.jit(f, lean=True) is f and B.jit(f, lean=False) is f and B.jit(f) is f
        return
    p = model.init_params(seed=1)
    u = B.asarray(np.random.default_rng(0).uniform(0.0, 1.0, (300, len(model.input_names))) + 0.5)
    T0 = B.asarray(np.full(len(model.state_names), 300.0))

    def run(T):
        return model.rollout(p, T, u, 1.0)[1]

    eye = B.asarray(np.eye(len(model.state_names)))

    def jac(T):
        return B.batched_jvp(run, (T,), (eye,))

    for f in (run, jac):
        g = B.no_grad(f) if f is run else f
        # the reference as a user's process compiles it: XLA's default code generation, whatever the test session's
        # XLA_FLAGS choose (conftest.LEAN_TEST_XLA_FLAG)
        ref = B.numpy(B.jax.jit(g, compiler_options=FUSED_XLA_OPTIONS)(T0))
        lean = B.numpy(B.jit(g, lean=True)(T0))
        assert np.all(np.isfinite(ref))
        np.testing.assert_allclose(lean, ref, rtol=1e-11, atol=1e-11 * np.abs(ref).max())
    assert _lean_options_accepted()
    assert B.lean_options() == {"xla_cpu_use_fusion_emitters": False}


def test_the_models_point_programs_and_steady_state_are_lean_from_python_and_nested_in_a_program():
    """The model's steady state and point evaluations (``LEAN_PROGRAMS``) are compiled with the lean options when
    called from Python, with the default inside another program (JAX refuses compiler options on a nested ``jit``:
    the doctor's Jacobians call ``model.rhs`` inside theirs): both give the eager numbers to round-off."""
    import jax

    import tnn_dsl
    from tnn_dsl.compiler.model import LEAN_PROGRAMS
    from tnn_dsl.studies.casestudy import network_path

    assert {"steady", "rhs", "outputs", "heat_flows"} <= set(LEAN_PROGRAMS) and "rollout" not in LEAN_PROGRAMS
    model = tnn_dsl.compile(tnn_dsl.load(network_path("peltier_heatpipe/m3.thn")), backend="jax")
    p = model.init_params(seed=1)
    u = np.full(len(model.input_names), 1.0)
    T = np.full(len(model.state_names), 300.0)
    top = {"rhs": model.rhs(p, T, u), "outputs": model.outputs(p, T, u), "steady": model.steady_state(p, u)}
    assert {k[0] for k in model._jit_cache if isinstance(k, tuple) and k[-1] is True} >= {"rhs", "outputs", "steady"}
    nested = jax.jit(lambda T, u: (model.rhs(p, T, u), model.outputs(p, T, u), model.steady_state(p, u)))(T, u)
    batched = jax.vmap(lambda T: model.rhs(p, T, u))(np.stack([T, T + 1.0]))
    eager = model._core.rhs(model._prepare(p), jax.numpy.asarray(T), jax.numpy.asarray(u))
    for a, b in zip((top["rhs"], top["outputs"], top["steady"]), nested):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(np.asarray(top["rhs"]), np.asarray(eager), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(batched[0]), np.asarray(top["rhs"]), rtol=1e-12, atol=1e-15)
    assert np.all(np.isfinite(np.asarray(top["steady"])))


def test_inside_lean_programs_the_training_s_programs_are_lean_and_nested_rollouts_work():
    """Inside ``lean_programs()`` (the doctor's linear-or-MLP check: two trainings whose compilation was the
    diagnosis' peak memory, issue 18) the programs ``jit`` and ``value_and_grad`` make, the model's rollout called from
    Python and the forward-mode Jacobian are compiled with the lean options, a rollout traced inside another program
    takes the enclosing one's (JAX refuses options on a nested ``jit``), and every number is the default program's
    to round-off; outside the block nothing changes."""
    import jax

    import tnn_dsl
    from tnn_dsl.compiler.backends.adapter import lean_programs, lean_programs_active
    from tnn_dsl.studies.casestudy import network_path

    model = tnn_dsl.compile(tnn_dsl.load(network_path("peltier_heatpipe/m1.thn")), backend="jax")
    B = backend_of(model)
    p = model.init_params(seed=1)
    u = np.random.default_rng(0).uniform(0.0, 1.0, (200, len(model.input_names))) + 0.5
    T0 = np.full(len(model.state_names), 300.0)
    name = next(k for k, s in model.param_specs.items() if s.kind == "physical" and s.trainable)

    def loss(z):
        q = dict(p)
        q[name] = z[0]
        return jax.numpy.sum(model.rollout(q, T0, u, 1.0)[1] ** 2)

    def run(z):
        return model.rollout(p, T0 + z, u, 1.0)[1]

    z0 = np.array([float(np.asarray(p[name]))])
    ref = (B.numpy(model.rollout(p, T0, u, 1.0)[1]), B.value_and_grad(loss)(z0), B.jacobian(run, np.zeros(len(T0))),
           B.numpy(B.jit(lambda T: model.rollout(p, T, u, 1.0)[1])(T0)))
    assert not lean_programs_active()
    with lean_programs():
        assert lean_programs_active()
        got = (B.numpy(model.rollout(p, T0, u, 1.0)[1]), B.value_and_grad(loss)(z0),
               B.jacobian(run, np.zeros(len(T0))), B.numpy(B.jit(lambda T: model.rollout(p, T, u, 1.0)[1])(T0)))
        assert any(isinstance(k, tuple) and k[0] == "rollout" and k[-1] is True for k in model._jit_cache)
    assert not lean_programs_active()
    for a, b in zip((ref[0], ref[1][0], ref[1][1], ref[2], ref[3]), (got[0], got[1][0], got[1][1], got[2], got[3])):
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_in_chunks_equals_one_batch(backend):
    """``Backend.batched(f, chunk=k)`` (the doctor's forward-difference Jacobians run their simulations a few at a
    time, issue 18) gives what one batch gives, for a batch that the chunk divides and one it does not."""
    import tnn_dsl
    from tnn_dsl.studies.casestudy import network_path

    model = tnn_dsl.compile(tnn_dsl.load(network_path("tclab/tclab.thn")), backend=backend)
    B = backend_of(model)
    p = model.init_params(seed=1)
    u = B.asarray(np.random.default_rng(0).uniform(0.0, 1.0, (120, len(model.input_names))))

    def run(T0):
        return model.rollout(p, T0, u, 1.0)[1]

    for m in (6, 7):
        T0 = B.asarray(300.0 + np.arange(m)[:, None] * np.ones(len(model.state_names)))
        whole = B.numpy(B.no_grad(B.batched(run))(T0))
        for chunk in (2, 3, 6):
            got = B.numpy(B.no_grad(B.batched(run, chunk=chunk))(T0))
            assert got.shape == whole.shape == (m, 120, len(model.output_names))
            np.testing.assert_allclose(got, whole, rtol=1e-12, atol=1e-12)


_CACHE_PROBE = """
import jax.monitoring, numpy as np
seen = set()
jax.monitoring.register_event_listener(lambda e, **k: seen.add(e))
import tnn_dsl
m = tnn_dsl.compile(tnn_dsl.load({net!r}))
m.rollout(m.init_params(seed=0), np.full(len(m.state_names), 300.0), np.full((50, len(m.input_names)), 0.5), 1.0)
print(sorted(e.rsplit('/', 1)[1] for e in seen if 'compilation_cache/cache_' in e))
"""


def test_a_cache_directory_in_the_environment_keeps_every_program(tmp_path):
    """With ``JAX_COMPILATION_CACHE_DIR`` set, a model's simulation — compiled in far less than the second below which
    JAX keeps nothing — is written to the cache, and the next process reads it instead of compiling it
    (``jax_ops.cache_every_program``, issue 18); a threshold the environment sets itself is left as it is."""
    import subprocess
    import sys

    code = _CACHE_PROBE.format(net=os.path.join(ROOT, "networks", "tclab", "tclab.thn"))

    def run(cache, **env):
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                             env={**os.environ, "JAX_COMPILATION_CACHE_DIR": str(cache), **env})
        assert out.returncode == 0, out.stderr[-2000:]
        return out.stdout.strip().splitlines()[-1]

    assert run(tmp_path / "c") == "['cache_misses']"
    def programs(cache) -> list[str]:  # JAX's own lock file aside
        return [p.name for p in cache.iterdir() if not p.name.startswith(".")] if cache.exists() else []

    assert programs(tmp_path / "c")
    assert run(tmp_path / "c") == "['cache_hits']"
    run(tmp_path / "d", JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1000")
    assert programs(tmp_path / "d") == []
