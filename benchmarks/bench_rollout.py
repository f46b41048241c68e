"""Per-step cost of a case-study rollout on JAX, torch, a numpy reference loop and a compiled C loop.

The network is ``networks/peltier_heatpipe/m3.thn`` (7 nodes, links, Peltier, two fluids, an 8×8 sigmoid
MLP for the three heat-pipe resistances) with random non-zero MLP weights (seeded), driven by the case
study's inputs (pseudo-random steps of I ∈ [0, 3] A and u1 ∈ [0, 1], hold 120–600 s; Ta 22 °C, fluids
25 °C), sample time 1 s, RK4 (the model's default integrator), float64.

Measured (each the median of ``--repeats`` runs; the first call — tracing, XLA compilation — is timed
apart and reported as warm-up; torch compiles cold, into an empty inductor cache of the run's own, unless
``--warm-torch-cache``):

* single sequence of ``--steps`` samples, forward (``model.rollout``) and forward + gradient of a scalar
  loss (mean squared error of ``T_out`` against a fixed reference) w.r.t. every trainable parameter;
* a batch of ``--batch`` windows that tile the same number of samples (``--window`` samples each,
  default ``steps // batch``), forward and forward + gradient;
* JAX and torch through the public model API (torch eager, and with ``torch_compile=True``: a forward
  rollout is one ``torch.compile``d ``scan`` over the samples, a rollout with gradients a forward and an
  adjoint scan, both with inductor's C++ wrapper; ``torchv``: the batch again with inductor's SIMD kernels, the
  model's ``TORCH_VECTORIZE``); the numpy reference backend (forward only, it has no
  autodiff); a C loop of the same equations (``_c_loop.py``, ``cc -O3 -march=native``), checked against
  JAX to ``1e-9 K`` on every state before it is timed.

Python-loop rollouts (torch, numpy) cost the same per step at any length, so they run on
``--slow-steps`` samples (default 5 000) to keep the benchmark short; the table says how many steps each
number is from. Prototypes of faster rollouts (not the model's code path) are measured too, to back the
speed-up proposals with numbers; they are checked against the model's rollout before timing.

Usage::

    python benchmarks/bench_rollout.py                       # full run, writes BENCHMARKS.md
    python benchmarks/bench_rollout.py --quick               # a few seconds' worth
    python benchmarks/bench_rollout.py --steps 2000 --batch 8 --repeats 1 --output /tmp/B.md --json r.json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from _c_loop import Unsupported, build_c_rollout  # noqa: E402
from _report import load_average, write_section  # noqa: E402

NET = ROOT / "networks" / "peltier_heatpipe" / "m3.thn"
C_TOL = 1e-9  # K: the C loop must agree with JAX to this before it is timed

# Targets of issue 3 (this 2-core machine).
TARGET_JAX_SINGLE_US = 1.0
TARGET_JAX_OVER_C = 3.0
TARGET_JAX_BATCH_US = 0.2
TARGET_GRAD_OVER_FWD = 4.0
TARGET_TORCH_OVER_JAX_BATCH = 5.0
# Targets of issue 18 (torch at JAX's speed).
TARGET_TORCH_OVER_JAX_SINGLE = 10.0
TARGET_TORCH_OVER_JAX_BATCH_GRAD = 2.0


# ---------------------------------------------------------------------------------------------
# The case
# ---------------------------------------------------------------------------------------------


def step_sequence(rng, n, lo, hi, dt, hold=(120.0, 600.0)):
    """Pseudo-random steps: levels uniform in [lo, hi], hold times uniform in ``hold`` seconds."""
    out = np.empty(n)
    k = 0
    while k < n:
        m = max(1, int(round(rng.uniform(*hold) / dt)))
        out[k:k + m] = rng.uniform(lo, hi)
        k += m
    return out


def case_inputs(model, n, dt, seed):
    """Inputs ``(n, n_inputs)`` SI in the model's input order (case-study spec)."""
    rng = np.random.default_rng(seed)
    cols = {"I": step_sequence(rng, n, 0.0, 3.0, dt), "u1": step_sequence(rng, n, 0.0, 1.0, dt),
            "Ta": np.full(n, 295.15), "Tf1": np.full(n, 298.15), "Tf2": np.full(n, 298.15)}
    return np.stack([cols[name] for name in model.input_names], axis=-1)


def random_weights(model, seed):
    """The model's numpy parameter table with every learned weight random and non-zero (seeded)."""
    rng = np.random.default_rng(seed)
    p = model._init_numpy(seed) if hasattr(model, "_init_numpy") else model.to_numpy(model.init_params(seed))
    for k, spec in model.param_specs.items():
        if spec.kind == "weights":
            scale = 0.5 if k.split(".")[-1].startswith("W") else 0.1
            p[k] = rng.uniform(-scale, scale, size=spec.shape)
    return p


class Case:
    """Everything the measurements share (numpy arrays)."""

    def __init__(self, args):
        import tnn_dsl

        self.net = tnn_dsl.load(NET)
        self.dt = float(args.dt)
        self.integrator = args.integrator
        self.steps = int(args.steps)
        self.batch = int(args.batch)
        self.window = int(args.window or max(2, self.steps // max(1, self.batch)))
        self.slow_steps = int(min(args.slow_steps, self.steps))
        self.slow_batch_window = int(min(self.window, max(2, args.slow_steps // max(1, self.batch))))
        ref = tnn_dsl.compile(self.net, "numpy")
        self.params = random_weights(ref, args.seed)
        self.trainable = [k for k, s in ref.param_specs.items() if s.trainable]
        self.U = case_inputs(ref, self.steps, self.dt, args.seed)
        # start at the steady state of the first inputs (case-study spec), numpy reference backend
        self.T0 = np.asarray(ref.steady_state(self.params, self.U[0]), dtype=np.float64)
        rng = np.random.default_rng(args.seed + 1)
        starts = np.arange(self.batch) * self.window % max(1, self.steps - self.window + 1)
        self.Ub = np.stack([self.U[s:s + self.window] for s in starts]) if self.window <= self.steps else \
            np.stack([case_inputs(ref, self.window, self.dt, args.seed + 2 + b) for b in range(self.batch)])
        self.T0b = self.T0 + rng.normal(0.0, 0.5, size=(self.batch, len(self.T0)))
        self.y_ref = 298.15  # K: the fixed reference of the scalar loss
        self.out_idx = list(self.net.node_names).index(self.net.sensors[0].node)  # the state T_out reads
        tau, _ = ref.fastest_time_constant()
        from tnn_dsl.compiler.integrators import stable_substeps

        self.substeps = stable_substeps(self.integrator, self.dt, tau)


# ---------------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------------


def measure(fn, repeats, budget_s=None):
    """``(warm-up s, median wall s, last result)``: the first call apart, then ``repeats`` timed calls (fewer
    if ``budget_s`` would be exceeded, at least one). The median process CPU time of the same calls (all
    threads) is left in ``measure.cpu`` — on a shared machine it is a steadier estimate of the work than the
    wall time."""
    t = time.perf_counter()
    out = fn()
    first = time.perf_counter() - t
    times, cpu = [], []
    for _ in range(max(1, repeats)):
        t, c = time.perf_counter(), time.process_time()
        out = fn()
        times.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
        if budget_s is not None and sum(times) > budget_s:
            break
    measure.cpu = statistics.median(cpu)
    return max(0.0, first - statistics.median(times)) + statistics.median(times), statistics.median(times), out


class Row:
    def __init__(self, impl, case, steps_each, windows, fwd=None, grad=None, warm_fwd=None, warm_grad=None,
                 note="", cpu=None):
        self.impl, self.case, self.steps_each, self.windows = impl, case, steps_each, windows
        self.cpu = cpu  # median process CPU time of the forward call (s)
        self.fwd, self.grad, self.warm_fwd, self.warm_grad, self.note = fwd, grad, warm_fwd, warm_grad, note

    @property
    def n_steps(self):  # integration steps in one call (all windows)
        return max(1, self.steps_each - 1) * self.windows

    def us(self, t):
        return None if t is None else t / self.n_steps * 1e6

    def as_dict(self):
        return {"impl": self.impl, "case": self.case, "steps": self.steps_each, "windows": self.windows,
                "fwd_us_per_step": self.us(self.fwd), "grad_us_per_step": self.us(self.grad),
                "grad_over_fwd": (self.grad / self.fwd) if self.fwd and self.grad else None,
                "fwd_cpu_us_per_step": self.us(self.cpu), "warmup_fwd_s": self.warm_fwd,
                "warmup_grad_s": self.warm_grad, "note": self.note}


# ---------------------------------------------------------------------------------------------
# Backends
# ---------------------------------------------------------------------------------------------


def bench_jax(case, args, rows, results, dtype="float64"):
    import jax
    import jax.numpy as jnp

    import tnn_dsl

    model = tnn_dsl.compile(case.net, "jax", dtype=dtype)
    tag = "" if dtype == "float64" else f"_{dtype}"
    p = model.from_numpy(case.params)
    dt, integ = case.dt, case.integrator

    def loss_fn(model, p, train, T0, U):
        full = {**p, **train}
        _, y = model.rollout(full, T0, U, dt, integ)
        return jnp.mean((y - case.y_ref) ** 2)

    vg = jax.jit(jax.value_and_grad(lambda train, T0, U: loss_fn(model, p, train, T0, U)))
    train = {k: p[k] for k in case.trainable}
    for label, T0, U, windows in (("single", case.T0, case.U, 1), ("batch", case.T0b, case.Ub, case.batch)):
        T0j, Uj = model.xp.asarray(T0), model.xp.asarray(U)

        def fwd():
            s, y = model.rollout(p, T0j, Uj, dt, integ)
            s.block_until_ready()
            return s

        def grad():
            v, g = vg(train, T0j, Uj)
            jax.block_until_ready(g)
            return v, g

        wf, tf, s = measure(fwd, args.repeats)
        cf = measure.cpu
        wg, tg, (_, g) = measure(grad, args.repeats)
        results[f"jax{tag}_states_{label}"] = np.asarray(s, dtype=np.float64)
        results[f"jax{tag}_grad_{label}"] = {k: np.asarray(v) for k, v in g.items()}
        note = ""
        if tag:
            d = float(np.max(np.abs(results[f"jax{tag}_states_{label}"] - results[f"jax_states_{label}"])))
            note = f"max abs diff from float64: {d:.2g} K"
        rows.append(Row("JAX" + (f" {dtype}" if tag else ""), label, U.shape[-2], windows, tf, tg, wf - tf, wg - tg,
                        cpu=cf, note=note))
    return model


def bench_torch(case, args, rows, results, compiled=False, vectorize=False):
    """torch through the model API, eager or with ``torch_compile=True`` (forward: one compiled ``scan``;
    with gradients: a forward and an adjoint scan), run with ``--torch-threads`` intra-op threads (default
    1: on this workload of tiny tensors, OpenMP threads cost far more than they give, most of all on a busy
    machine); the eager batch
    forward is also timed with torch's default thread count to show the difference. ``vectorize``: compiled
    with inductor's SIMD kernels (the model's ``TORCH_VECTORIZE`` on while this runs), the batch only."""
    import torch

    import tnn_dsl
    import tnn_dsl.compiler.model as compiled_model

    model = tnn_dsl.compile(case.net, "torch", torch_compile=compiled)
    impl, tag = ("torch (torch_compile=True)", "torchc_") if compiled else ("torch (eager)", "torch_")
    if vectorize:
        impl, tag = "torch (torch_compile=True, SIMD kernels)", "torchv_"
    cases = [("single", case.T0, case.U[:case.slow_steps], 1),
             ("batch", case.T0b, case.Ub[:, :case.window], case.batch)][1 if vectorize else 0:]
    dt, integ = case.dt, case.integrator
    default_threads = torch.get_num_threads()
    torch.set_num_threads(args.torch_threads)
    vectorize_before = compiled_model.TORCH_VECTORIZE
    compiled_model.TORCH_VECTORIZE = bool(vectorize) or vectorize_before
    try:
        for label, T0, U, windows in cases:
            T0t, Ut = torch.as_tensor(T0), torch.as_tensor(U)
            p = model.from_numpy(case.params)

            def fwd():
                with torch.no_grad():
                    return model.rollout(p, T0t, Ut, dt, integ)[0]

            def grad():
                pg = dict(p)
                for k in case.trainable:
                    pg[k] = p[k].detach().clone().requires_grad_(True)
                _, y = model.rollout(pg, T0t, Ut, dt, integ)
                loss = torch.mean((y - case.y_ref) ** 2)
                loss.backward()
                return {k: pg[k].grad for k in case.trainable}

            wf, tf, s = measure(fwd, args.repeats, budget_s=args.budget)
            cf = measure.cpu
            wg, tg, g = measure(grad, args.repeats, budget_s=args.budget)
            results[f"{tag}states_{label}"] = s.numpy()
            results[f"{tag}grad_{label}"] = {k: v.numpy() for k, v in g.items()}
            rows.append(Row(impl, label, U.shape[-2], windows, tf, tg, wf - tf, wg - tg,
                            note=f"torch.set_num_threads({args.torch_threads})", cpu=cf))
            if label == "batch" and default_threads != args.torch_threads and not compiled:
                torch.set_num_threads(default_threads)
                wf, tf, _ = measure(fwd, args.repeats, budget_s=args.budget)
                cf = measure.cpu
                torch.set_num_threads(args.torch_threads)
                rows.append(Row(f"torch (eager, {default_threads} threads)", label, U.shape[-2], windows, tf, None,
                                wf - tf, None, note="torch's default thread count", cpu=cf))
    finally:
        torch.set_num_threads(default_threads)
        compiled_model.TORCH_VECTORIZE = vectorize_before
    return model


def bench_numpy(case, args, rows, results):
    import tnn_dsl

    model = tnn_dsl.compile(case.net, "numpy")
    for label, T0, U, windows in (("single", case.T0, case.U[:case.slow_steps], 1),
                                  ("batch", case.T0b, case.Ub[:, :case.slow_batch_window], case.batch)):
        def fwd():
            return model.rollout(case.params, T0, U, case.dt, case.integrator)[0]

        wf, tf, s = measure(fwd, args.repeats, budget_s=args.budget)
        cf = measure.cpu
        results[f"numpy_states_{label}"] = np.asarray(s)
        rows.append(Row("numpy reference", label, U.shape[-2], windows, tf, None, wf - tf, None,
                        note="forward only (no autodiff)", cpu=cf))


def bench_c(case, args, rows, results, jax_model):
    """The C loop; returns ``(max |C − JAX| over states (K), compile s)`` or raises Unsupported."""
    c = build_c_rollout(jax_model, case.params, case.dt, case.integrator, case.substeps)
    try:
        err = 0.0
        S = c.rollout(case.T0, case.U)
        err = max(err, float(np.max(np.abs(S - results["jax_states_single"]))))
        Sb = c.rollout_batch(case.T0b, case.Ub)
        err = max(err, float(np.max(np.abs(Sb - results["jax_states_batch"]))))
        results["c_max_abs_diff_K"] = err
        results["c_spec"] = c.spec
        if not err <= C_TOL:
            raise RuntimeError(f"the C loop disagrees with JAX by {err:.3g} K (> {C_TOL:g} K); not timing it")
        out1 = np.empty_like(S)
        outb = np.empty_like(Sb)
        _, tf, _ = measure(lambda: c.rollout(case.T0, case.U, out=out1), args.repeats)
        cf1 = measure.cpu
        _, tb, _ = measure(lambda: c.rollout_batch(case.T0b, case.Ub, out=outb), args.repeats)
        cfb = measure.cpu
        note = " ".join(a for a in c.command if a.startswith("-") and a not in ("-o", "-shared", "-fPIC"))
        rows.append(Row("C loop", "single", case.steps, 1, tf, None, c.compile_seconds, None, note=note, cpu=cf1))
        rows.append(Row("C loop", "batch", case.window, case.batch, tb, None, c.compile_seconds, None, note=note,
                        cpu=cfb))
        return err
    finally:
        c.close()


# ---------------------------------------------------------------------------------------------
# Prototypes behind the proposals (not the model's code path)
# ---------------------------------------------------------------------------------------------


def _proto_xp(dtype, small_matmul=False, fast_transcendentals=False, library_dots=False):
    """A JAX namespace for prototypes. ``small_matmul``: a product by a small constant matrix is a broadcast
    multiply + sum (XLA fuses it with its neighbours; a ``dot`` is a separate library call on CPU).
    ``library_dots``: the namespace as it was before issue 3's speed work (every product a ``jnp.matmul``,
    ``sigmoid`` XLA's ``logistic``), to show in one run what the model's namespace gains.
    ``fast_transcendentals``: ``sigmoid(x) = ½ + ½·tanh(x/2)`` and ``softplus(x) = max(x, 0) +
    log1p(exp(−|x|))`` (XLA's ``logistic`` and ``logaddexp`` are several times slower than ``tanh`` on CPU)."""
    import jax.numpy as jnp

    from tnn_dsl.compiler.backends.jax_ops import JaxXP

    class ProtoXP(JaxXP):
        pass

    if small_matmul:
        def matmul(a, b):
            a, b = jnp.asarray(a), jnp.asarray(b)
            if b.ndim == 2 and a.ndim >= 1 and b.shape[0] * b.shape[1] <= 256:
                return jnp.sum(a[..., :, None] * b, axis=-2)
            return jnp.matmul(a, b)
        ProtoXP.matmul = staticmethod(matmul)
    if library_dots:
        import jax

        ProtoXP.matmul = staticmethod(jnp.matmul)
        ProtoXP.sigmoid = staticmethod(jax.nn.sigmoid)
    if fast_transcendentals:
        ProtoXP.sigmoid = staticmethod(lambda x: 0.5 + 0.5 * jnp.tanh(0.5 * x))
        ProtoXP.softplus = staticmethod(lambda x: jnp.maximum(x, 0.0) + jnp.log1p(jnp.exp(-jnp.abs(x))))
    return ProtoXP(dtype)


def _jax_proto_rollout(model, core, unroll, integ, dt, sub):
    """A rollout like ``Model._rollout_impl`` (states only) with the model's own ``prepare``/``rhs`` from
    ``core`` and ``lax.scan(unroll=...)``."""
    import jax

    from tnn_dsl.compiler.integrators import euler, rk4

    method = rk4 if integ == "rk4" else euler
    h = dt / sub

    @jax.jit
    def roll(p, T0, U):
        prep = core.prepare(p)
        Us = jax.numpy.moveaxis(U, -2, 0)

        def body(T, u):
            for _ in range(sub):
                T = method(lambda x: core.rhs(prep, x, u), T, h)
            return T, T

        _, rest = jax.lax.scan(body, T0, Us[:-1], unroll=unroll)
        return jax.numpy.moveaxis(jax.numpy.concatenate([T0[None], rest], axis=0), 0, -2)

    return roll


def _unrolled_rhs(spec, xp_sigmoid="tanh", batch_last=False):
    """A right-hand side built from the C loop's element tables (``_c_loop`` ``spec``) as unrolled
    per-element JAX expressions: no matmul, no stack of a dict, every node's heat balance a sum of scalars
    (``(...,)`` arrays when batched), so XLA fuses the whole right-hand side into a few kernels.
    ``rhs(p, T (..., n), u (..., n_in)) -> dT (..., n)``; ``p`` the model's parameter table (traced:
    gradients flow to the Peltier coefficients and the MLP arrays; the other constants are folded in).
    With ``batch_last`` the arrays are ``T (n, ...)``, ``u (n_in, ...)``: every per-element quantity is then a
    contiguous row of the batch, which XLA vectorises."""
    import jax.numpy as jnp

    n = spec["n"]
    consts = spec["consts"]
    invC = [1.0 / consts[c] for c in spec["invC_names"]]
    sp4 = math.log1p(math.exp(4.0))
    mlp = spec["mlp"]

    def sig(x):
        return 0.5 + 0.5 * jnp.tanh(0.5 * x) if xp_sigmoid == "tanh" else 1.0 / (1.0 + jnp.exp(-x))

    def act(x):
        return sig(x) if mlp["activation"] == "sigmoid" else jnp.tanh(x)

    def softplus(x):
        return jnp.maximum(x, 0.0) + jnp.log1p(jnp.exp(-jnp.abs(x)))

    def rhs(p, T, u):
        if batch_last:
            T = _Rows(T)
            u = _Rows(u)
        V = [T[..., i] for i in range(n)]
        for j, bi in enumerate(spec["b_in"]):
            if bi < 0:
                raise Unsupported("constant boundaries are not in the unrolled prototype")
            V.append(u[..., bi])
        Q = [0.0] * n

        def flow(a, b, g):
            q = g * (V[b] - V[a])
            if a < n:
                Q[a] = Q[a] + q
            if b < n:
                Q[b] = Q[b] - q

        for a, b, g in spec["ls"]:
            flow(a, b, g)
        if mlp is not None:
            name = mlp["name"]
            xm, xs = p[f"{name}.x_mean"], p[f"{name}.x_scale"]
            h = [((u[..., k] if kind else T[..., k]) - xm[j]) / xs[j]
                 for j, (kind, k) in enumerate(zip(mlp["x_kind"], mlp["x_idx"]))]
            for layer in range(mlp["n_layers"]):
                W, b = p[f"{name}.W{layer}"], p[f"{name}.b{layer}"]
                out = []
                for jj in range(W.shape[1]):
                    s = b[jj]
                    for ii in range(W.shape[0]):
                        s = s + h[ii] * W[ii, jj]
                    out.append(s if layer == mlp["n_layers"] - 1 else act(s))
                h = out
            z = h
        for a, b, k, is_r, pos, nom in spec["ld"]:
            v = nom * softplus(4.0 * (1.0 + z[k])) / sp4 if pos else nom + z[k]
            flow(a, b, 1.0 / v if is_r else v)
        for hh, c, i_in, s_name, r_name in spec["pe"]:
            if i_in < 0:
                raise Unsupported("constant Peltier current is not in the unrolled prototype")
            current = u[..., i_in]
            S, R = p[s_name], p[r_name]
            joule = 0.5 * R * current * current
            if hh < n:
                Q[hh] = Q[hh] + S * V[hh] * current + joule
            if c < n:
                Q[c] = Q[c] - S * V[c] * current + joule
        for node, G, i_in in spec["fluids"]:
            Q[node] = Q[node] + G * (u[..., i_in] - V[node])
        return jnp.stack([Q[i] * invC[i] + 0.0 * T[..., i] for i in range(n)], axis=0 if batch_last else -1)

    return rhs


class _Rows:
    """``x[..., i]`` on a batch-last array reads row ``i`` (``x[i]``)."""

    def __init__(self, x):
        self.x = x

    def __getitem__(self, key):
        return self.x[key[1]]


def _unrolled_rollout(spec, unroll=1, batch_last=False):
    """``roll(p, T0 (..., n), U (..., N, n_in)) -> states (..., N, n)`` with :func:`_unrolled_rhs`; with
    ``batch_last`` the scan carries ``T (n, B)`` (transposed once on the way in and out)."""
    import jax

    from tnn_dsl.compiler.integrators import euler, rk4

    rhs = _unrolled_rhs(spec, batch_last=batch_last)
    method = rk4 if spec["integrator"] == "rk4" else euler
    sub = spec["substeps"]
    h = spec["dt"] / sub

    @jax.jit
    def roll(p, T0, U):
        jnp = jax.numpy
        if batch_last and T0.ndim == 2:
            Us = jnp.transpose(U, (1, 2, 0))  # (N, n_in, B)
            T0t = T0.T  # (n, B)
        else:
            Us, T0t = jnp.moveaxis(U, -2, 0), T0

        def body(T, u):
            for _ in range(sub):
                T = method(lambda x: rhs(p, x, u), T, h)
            return T, T

        _, rest = jax.lax.scan(body, T0t, Us[:-1], unroll=unroll)
        S = jnp.concatenate([T0t[None], rest], axis=0)  # (N, n[, B])
        if batch_last and T0.ndim == 2:
            return jnp.transpose(S, (2, 0, 1))
        return jnp.moveaxis(S, 0, -2)

    return roll


def bench_jax_prototypes(case, args, rows, results, jax_model):
    import jax
    import jax.numpy as jnp

    from tnn_dsl.compiler.core import _Core

    p = jax_model.from_numpy(case.params)
    integ, dt, sub = case.integrator, case.dt, case.substeps
    out = {}
    variants = []
    # the model's own _Core.rhs (no input hoisting, no checkpointing) on the pre-issue-3 namespace and on the
    # model's namespace: what the namespace alone gains, in this run
    for name, kw in (("core.rhs, library dots + logistic (old namespace)", {"library_dots": True}),
                     ("core.rhs, model namespace", {})):
        core = _Core(jax_model._plan, _proto_xp("float64", **kw))
        variants.append((name, _jax_proto_rollout(jax_model, core, 1, integ, dt, sub)))
    if "c_spec" in results and "unrolled" in args.only:  # slower: kept to show it (see the report)
        variants.append(("unrolled per-element rhs", _unrolled_rollout(results["c_spec"])))
        variants.append(("unrolled per-element rhs, batch-last layout",
                         _unrolled_rollout(results["c_spec"], batch_last=True)))
    for name, roll in variants:
        def loss(train, T0, U, roll=roll):
            return jnp.mean((roll({**p, **train}, T0, U)[..., case.out_idx] - case.y_ref) ** 2)

        vg = jax.jit(jax.value_and_grad(loss))
        train = {k: p[k] for k in case.trainable}
        for label, T0, U, windows in (("single", case.T0, case.U, 1), ("batch", case.T0b, case.Ub, case.batch)):
            T0j, Uj = jnp.asarray(T0), jnp.asarray(U)
            S = np.asarray(roll(p, T0j, Uj))
            err = float(np.max(np.abs(S - results[f"jax_states_{label}"])))
            out[f"{name} / {label}"] = err
            if err > C_TOL:
                print(f"prototype {name!r} ({label}) differs from the model by {err:.3g} K; skipped", file=sys.stderr)
                continue
            wf, tf, _ = measure(lambda: roll(p, T0j, Uj).block_until_ready(), args.repeats)
            cf = measure.cpu
            wg, tg, _ = measure(lambda: jax.block_until_ready(vg(train, T0j, Uj)), args.repeats)
            rows.append(Row(f"JAX prototype: {name}", label, U.shape[-2], windows, tf, tg, wf - tf, wg - tg, cpu=cf))
    results["jax_prototype_max_abs_diff_K"] = out


def bench_xla_elementwise(case, results):
    """ns per element of XLA's transcendental functions on a (256, 8) array (the batched MLP layer), float64
    and float32, and the floor they put under a batched window-step: RK4 evaluates the right-hand side 4
    times, each with one activation per hidden unit and one softplus per positive learned target."""
    import jax
    import jax.numpy as jnp

    fns = {"exp": lambda x: jnp.exp(-jnp.abs(x)), "sigmoid (logistic)": jax.nn.sigmoid,
           "sigmoid via tanh": lambda x: 0.5 + 0.5 * jnp.tanh(0.5 * x), "softplus": jax.nn.softplus,
           "add+mul": lambda x: x * 1.0001 + 0.1}
    out = {}
    reps = 50
    for dtype in ("float64", "float32"):
        x = jnp.asarray(np.random.default_rng(0).normal(size=(256, 8)), dtype=dtype)
        for name, f in fns.items():
            def chain(x, f=f):
                for _ in range(reps):
                    x = f(x) * 0.5
                return x
            g = jax.jit(chain)
            _, t, _ = measure(lambda: g(x).block_until_ready(), 7)
            out[(name, dtype)] = t / reps / x.size * 1e9
    n_eval = 4 if case.integrator == "rk4" else 1
    n_act = sum(sum(int(h) for h in fn.hidden) for fn in case.net.learned if fn.kind == "mlp")
    n_sp = sum(1 for fn in case.net.learned for t in fn.targets if t.kind == "param")
    # the model's namespace computes sigmoid as ½ + ½·tanh(x/2) (jax_ops.sigmoid)
    floor = {dt: n_eval * (n_act * out[("sigmoid via tanh", dt)] + n_sp * out[("softplus", dt)]) / 1e3
             for dt in ("float64", "float32")}
    results["xla_elementwise_ns"] = {f"{k[0]} {k[1]}": v for k, v in out.items()}
    results["xla_transcendental_floor_us"] = floor
    results["xla_counts"] = (n_eval, n_act, n_sp)


# ---------------------------------------------------------------------------------------------
# Report
# ---------------------------------------------------------------------------------------------


def _f(x, fmt="{:.3g}"):
    return "—" if x is None or (isinstance(x, float) and not math.isfinite(x)) else fmt.format(x)


def _pf(ok):
    return "—" if ok is None else ("**pass**" if ok else "**FAIL**")


def find(rows, impl, case):
    for r in rows:
        if r.impl == impl and r.case == case:
            return r
    return None


def targets(rows):
    """``[(what, value, target text, pass?)]`` for the issue's targets."""
    js, jb = find(rows, "JAX", "single"), find(rows, "JAX", "batch")
    cs = find(rows, "C loop", "single")
    tb = find(rows, "torch (eager)", "batch")
    tcb = find(rows, "torch (torch_compile=True)", "batch")
    out = []

    def ratio(a, b):
        return None if a is None or b is None or not b else a / b

    if js:
        v = js.us(js.fwd)
        out.append(("JAX single sequence, forward (µs/step)", v, "≤ 1", v <= TARGET_JAX_SINGLE_US))
        if cs:
            v = ratio(js.us(js.fwd), cs.us(cs.fwd))
            out.append(("JAX / C loop, single sequence forward", v, "≤ 3×", v <= TARGET_JAX_OVER_C))
    if jb:
        v = jb.us(jb.fwd)
        out.append(("JAX batch, forward (µs per window-step)", v, "≤ 0.2", v <= TARGET_JAX_BATCH_US))
    for r in (js, jb):
        if r and r.grad:
            v = r.grad / r.fwd
            out.append((f"JAX {r.case}: forward+gradient / forward", v, "≤ 4×", v <= TARGET_GRAD_OVER_FWD))
    tcs = find(rows, "torch (torch_compile=True)", "single")
    if tcs and js:
        v = ratio(tcs.us(tcs.fwd), js.us(js.fwd))
        out.append(("torch (torch_compile=True) / JAX, single sequence forward (issue 18)", v, "≤ 10×",
                    v <= TARGET_TORCH_OVER_JAX_SINGLE))
    if tcb and jb:
        v = ratio(tcb.us(tcb.grad), jb.us(jb.grad))
        if v is not None:
            out.append(("torch (torch_compile=True) / JAX, batch forward+gradient (issue 18)", v, "≤ 2×",
                        v <= TARGET_TORCH_OVER_JAX_BATCH_GRAD))
    tvb = find(rows, "torch (torch_compile=True, SIMD kernels)", "batch")
    if tvb and jb:
        v = ratio(tvb.us(tvb.grad), jb.us(jb.grad))
        if v is not None:
            out.append(("torch (torch_compile=True, SIMD kernels) / JAX, batch forward+gradient (issue 18)", v,
                        "≤ 2×", v <= TARGET_TORCH_OVER_JAX_BATCH_GRAD))
    for r, how in ((tcb, "torch (torch_compile=True)"), (tb, "torch eager")):
        if r and jb:
            v = ratio(r.us(r.fwd), jb.us(jb.fwd))
            out.append((f"{how} / JAX, batch forward (per window-step)", v, "≤ 5×",
                        v <= TARGET_TORCH_OVER_JAX_BATCH))
            v = ratio(r.us(r.grad), jb.us(jb.grad))
            if v is not None:
                out.append((f"{how} / JAX, batch forward+gradient", v, "≤ 5×", v <= TARGET_TORCH_OVER_JAX_BATCH))
    return out


def markdown(case, args, rows, results, load_before, load_after, wall):
    lines = [
        f"Case study M3 (`{NET.relative_to(ROOT)}`: 7 nodes, 10 links, Peltier, 2 fluids, 4→8→8→3 sigmoid MLP "
        f"for the heat-pipe resistances, random non-zero weights, seed {args.seed}); {case.integrator} at "
        f"dt = {case.dt:g} s ({case.substeps} sub-step(s)), float64. Single sequence: {case.steps} samples; "
        f"batch: {case.batch} windows × {case.window} samples. Gradient: of the mean squared `T_out` error "
        f"w.r.t. all {len(case.trainable)} trainable arrays ({', '.join(case.trainable)}).",
        "",
        f"Times are wall-clock medians of {args.repeats} runs after a warm-up call (Python-loop rollouts stop "
        f"repeating after {args.budget:g} s); µs/step = time / integration steps (all windows). Warm-up = first "
        f"call − median (tracing, XLA or inductor compilation). 'forward CPU' is the median process CPU time "
        f"(all threads) of the same calls, steadier than wall time on a busy machine. Load average (1 min) "
        f"{load_before} before, {load_after} after; wall time {wall:.0f} s. **The machine is shared** (2 cores; "
        f"other jobs were running whenever the load is above ~2): absolute numbers are noisy; the ratios come "
        f"from this one run.",
        "",
        "| implementation | case | steps × windows | forward µs/step | fwd+grad µs/step | grad/fwd | "
        "forward CPU µs/step | warm-up fwd s | warm-up grad s | note |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        unit = " (per window-step)" if r.windows > 1 else ""
        lines.append(
            f"| {r.impl} | {r.case}{unit} | {r.steps_each} × {r.windows} | {_f(r.us(r.fwd))} | {_f(r.us(r.grad))} | "
            f"{_f(r.grad / r.fwd if r.fwd and r.grad else None, '{:.2f}')} | {_f(r.us(r.cpu))} | "
            f"{_f(r.warm_fwd, '{:.2f}')} | "
            f"{_f(r.warm_grad, '{:.2f}')} | {r.note} |")
    lines += ["", "Targets (issue 3):", "", "| quantity | measured | target | |", "|---|---|---|---|"]
    for what, v, tgt, ok in targets(rows):
        lines.append(f"| {what} | {_f(v)} | {tgt} | {_pf(ok)} |")
    if "c_max_abs_diff_K" in results:
        lines += ["", f"C loop vs JAX, max |ΔT| over all states and steps (single + batch): "
                      f"{results['c_max_abs_diff_K']:.2e} K (required ≤ {C_TOL:g} K before timing)."]
    if "c_error" in results:
        lines += ["", f"C loop: not measured ({results['c_error']})."]
    for key in ("torch_grad_agree", "torch_states_agree"):
        if key in results:
            lines.append(f"{key.replace('_', ' ')}: {results[key]}")
    if "torch_compile_error" in results:
        lines += ["", f"torch with torch_compile=True: not measured ({results['torch_compile_error']})."]
    if "torch_vectorize_error" in results:
        lines += ["", f"torch with SIMD kernels: not measured ({results['torch_vectorize_error']})."]
    if "xla_elementwise_ns" in results:
        ns = results["xla_elementwise_ns"]
        n_eval, n_act, n_sp = results["xla_counts"]
        fl = results["xla_transcendental_floor_us"]
        lines += ["", "XLA CPU cost per element on a (256, 8) array (ns): "
                  + ", ".join(f"{k} {v:.2g}" for k, v in ns.items()) + ".",
                  f"A window-step evaluates the right-hand side {n_eval}× with {n_act} activations and {n_sp} "
                  f"softplus each, so these functions alone cost ≥ {fl['float64']:.2g} µs per window-step in "
                  f"float64 ({fl['float32']:.2g} µs in float32) with XLA on this machine."]
    return "\n".join(lines)


def agreement(results):
    """torch vs JAX on the common prefix of states; gradients on equal lengths only (batch windows)."""
    out = {}
    for tag in ("torch", "torchc", "torchv"):
        for label in ("single", "batch"):
            a, b = results.get(f"{tag}_states_{label}"), results.get(f"jax_states_{label}")
            if a is not None and b is not None:
                n = a.shape[-2]
                out[f"{tag}_vs_jax_states_{label}_K"] = float(np.max(np.abs(a - b[..., :n, :])))
        ga, gb = results.get(f"{tag}_grad_batch"), results.get("jax_grad_batch")
        if ga and gb and results["jax_states_batch"].shape == results.get(f"{tag}_states_batch", np.empty(0)).shape:
            rel = 0.0
            for k in ga:
                d = np.max(np.abs(ga[k] - gb[k])) / max(np.max(np.abs(gb[k])), 1e-300)
                rel = max(rel, float(d))
            out[f"{tag}_vs_jax_grad_batch_rel"] = rel
    return out


def parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=100_000, help="samples of the single sequence (default 100000)")
    ap.add_argument("--batch", type=int, default=256, help="windows in the batch (default 256)")
    ap.add_argument("--window", type=int, default=None, help="samples per window (default steps // batch)")
    ap.add_argument("--slow-steps", type=int, default=5_000,
                    help="samples for Python-loop rollouts (torch eager, numpy; default 5000)")
    ap.add_argument("--repeats", type=int, default=5, help="timed repeats; the median is reported (default 5)")
    ap.add_argument("--budget", type=float, default=60.0,
                    help="seconds per slow measurement before it stops repeating (default 60)")
    ap.add_argument("--torch-threads", type=int, default=1,
                    help="torch intra-op threads for the torch rows (default 1; see the report)")
    ap.add_argument("--torch-chunk", type=int, default=None,
                    help="samples per iteration of the compiled torch scan on a single sequence (default: the "
                         "model's TORCH_CHUNK); to compare chunk sizes")
    ap.add_argument("--torch-grad-chunk", type=int, default=None,
                    help="sample intervals unrolled per compiled graph by torch rollouts with gradients (default: "
                         "the model's TORCH_GRAD_CHUNK; 1 = one compiled call per step); to compare chunk sizes")
    ap.add_argument("--warm-torch-cache", action="store_true",
                    help="let torch reuse inductor's default on-disk cache (default: an empty one for this run, so "
                         "the compile times are a first run's)")
    ap.add_argument("--torch-python-wrapper", action="store_true",
                    help="compile the torch forward scan with inductor's Python wrapper (the model's "
                         "TORCH_CPP_WRAPPER = False); combine with --torch-chunk 4, that wrapper's best")
    ap.add_argument("--torch-step-path", action="store_true",
                    help="torch_compile rollouts with gradients step by step (the model's TORCH_ADJOINT = False) "
                         "instead of a forward and an adjoint scan; to compare the two")
    ap.add_argument("--dt", type=float, default=1.0, help="sample time, s (default 1, the case study's)")
    ap.add_argument("--integrator", choices=("rk4", "euler"), default="rk4")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--only", default="jax,f32,torch,torchc,torchv,numpy,c,proto",
                    help="comma list of jax, f32 (JAX in float32), torch (eager), torchc (torch_compile=True), "
                         "torchv (torch_compile=True with inductor's SIMD kernels, the batch only), "
                         "numpy, c, proto (prototypes), unrolled "
                         "(the slow unrolled-rhs prototypes; off by default); jax is always run")
    ap.add_argument("--quick", action="store_true",
                    help="a short run: 4000 steps, batch 16, 3 repeats, 500 slow steps, no prototypes (unless given)")
    ap.add_argument("--output", default=str(ROOT / "BENCHMARKS.md"), help="markdown file to update")
    ap.add_argument("--no-write", action="store_true", help="print the section instead of writing it")
    ap.add_argument("--json", default=None, help="also write the raw results as JSON here")
    args = ap.parse_args(argv)
    if args.quick:
        given = set(a.split("=")[0] for a in (argv if argv is not None else sys.argv[1:]))
        for opt, val in (("--steps", 4000), ("--batch", 16), ("--repeats", 3), ("--slow-steps", 500),
                         ("--only", "jax,torch,numpy,c")):
            if opt not in given:
                setattr(args, opt[2:].replace("-", "_"), val)
    if args.steps < 2 or args.batch < 1 or args.repeats < 1 or args.slow_steps < 2:
        ap.error("--steps and --slow-steps must be >= 2, --batch and --repeats >= 1")
    return args


def main(argv=None):
    args = parse(argv)
    cold = None
    if not args.warm_torch_cache and "torch" not in sys.modules:  # before torch reads its configuration
        import os
        import tempfile

        cold = tempfile.TemporaryDirectory(prefix="tnn_bench_inductor_")
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = cold.name
    only = {s.strip() for s in args.only.split(",") if s.strip()}
    if args.torch_chunk is not None:
        import tnn_dsl.compiler.model as compiled_model

        compiled_model.TORCH_CHUNK = int(args.torch_chunk)
    if args.torch_grad_chunk is not None:
        import tnn_dsl.compiler.model as compiled_model

        compiled_model.TORCH_GRAD_CHUNK = int(args.torch_grad_chunk)
        compiled_model.TORCH_ADJOINT = False  # the chunks are the step-by-step path's
    if args.torch_python_wrapper:
        import tnn_dsl.compiler.model as compiled_model

        compiled_model.TORCH_CPP_WRAPPER = False
    if args.torch_step_path:
        import tnn_dsl.compiler.model as compiled_model

        compiled_model.TORCH_ADJOINT = False
    warnings.simplefilter("ignore", category=UserWarning)  # step-size warnings are reported via substeps
    load_before = load_average().split()[0] if load_average() != "n/a" else "n/a"
    t_start = time.perf_counter()
    case = Case(args)
    rows: list[Row] = []
    results: dict = {}
    print(f"case: {case.steps} steps, batch {case.batch} × {case.window}, {case.integrator}, "
          f"{case.substeps} sub-step(s)", file=sys.stderr)
    jax_model = bench_jax(case, args, rows, results)
    if "f32" in only:
        bench_jax(case, args, rows, results, dtype="float32")
    print("jax done", file=sys.stderr)
    if "c" in only:
        try:
            bench_c(case, args, rows, results, jax_model)
        except Unsupported as e:
            results["c_error"] = str(e)
        print("c done", file=sys.stderr)
    if "torch" in only:
        bench_torch(case, args, rows, results)
        print("torch done", file=sys.stderr)
    if "torchc" in only:
        try:
            bench_torch(case, args, rows, results, compiled=True)
        except Exception as e:  # noqa: BLE001 - inductor needs a C++ toolchain; report instead of failing
            results["torch_compile_error"] = f"{type(e).__name__}: {str(e)[:300]}"
        print("torch (torch_compile=True) done", file=sys.stderr)
    if "torchv" in only:
        try:
            bench_torch(case, args, rows, results, compiled=True, vectorize=True)
        except Exception as e:  # noqa: BLE001 - as above
            results["torch_vectorize_error"] = f"{type(e).__name__}: {str(e)[:300]}"
        print("torch (torch_compile=True, SIMD kernels) done", file=sys.stderr)
    if "numpy" in only:
        bench_numpy(case, args, rows, results)
        print("numpy done", file=sys.stderr)
    if "proto" in only:
        bench_jax_prototypes(case, args, rows, results, jax_model)
        bench_xla_elementwise(case, results)
        print("prototypes done", file=sys.stderr)
    results.update(agreement(results))
    wall = time.perf_counter() - t_start
    load_after = load_average().split()[0] if load_average() != "n/a" else "n/a"
    md = markdown(case, args, rows, results, load_before, load_after, wall)
    print(md)
    if not args.no_write:
        write_section("rollout", md, path=args.output,
                      title="Rollout cost: case study M3 (JAX, torch, numpy, C loop)")
    if args.json:
        payload = {"rows": [r.as_dict() for r in rows],
                   "targets": [{"what": w, "value": v, "target": t, "pass": ok} for w, v, t, ok in targets(rows)],
                   "c_max_abs_diff_K": results.get("c_max_abs_diff_K"), "c_error": results.get("c_error"),
                   "agreement": {k: v for k, v in results.items() if k.startswith("torch_vs_jax")},
                   "jax_prototype_max_abs_diff_K": results.get("jax_prototype_max_abs_diff_K"),
                   "torch_compile_error": results.get("torch_compile_error"),
                   "xla_elementwise_ns": results.get("xla_elementwise_ns"),
                   "xla_transcendental_floor_us": results.get("xla_transcendental_floor_us"),
                   "steps": case.steps, "batch": case.batch, "window": case.window,
                   "load_before": load_before, "load_after": load_after, "wall_s": wall}
        Path(args.json).write_text(json.dumps(payload, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
