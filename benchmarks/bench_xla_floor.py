"""What XLA on this CPU costs before any thermal network is in it: the floor under issue 3's absolute targets.

Two measurements, each the median of ``--repeats`` runs after a warm-up call, float64:

1. **Per-kernel cost in a loop** (the single-sequence floor): a ``lax.scan`` whose body is a chain of K
   dependent "layers" ``x ← tanh(W_k·x) + 0.01`` on an 8-vector — each layer one XLA fusion (a product whose
   operand is read 8 times cannot be fused with the expensive ``tanh`` before it) — for K = 5, 10, 20; the
   slope is the cost of one fusion in the loop body (dispatch + its tiny work). The fusions in the loop body of
   the model's own compiled single-sequence rollout of M3 (``networks/peltier_heatpipe/m3.thn``, RK4) are
   counted in its optimised HLO; times the cost per fusion, that is the single-sequence floor.
2. **A skeleton of the batched case-study step** (256 windows × 390 steps, RK4): an MLP 4→8→8→3 and the network
   as small products, with and without the transcendental functions (tanh-sigmoid, softplus), with the batch
   as the leading axis (the model's layout) and as the trailing axis. The cheapest variant — no
   transcendentals at all — is a lower bound for any XLA rollout of the M3 step in that layout.
3. **The model ladder**: the model's own rollout of M1 (constant resistances), M2 (linear) and M3 (MLP),
   single sequence and batch, with the fusions in each loop body.

    python benchmarks/bench_xla_floor.py            # writes the `xla-floor` section of BENCHMARKS.md
    python benchmarks/bench_xla_floor.py --no-write
"""

from __future__ import annotations

import argparse
import re
import statistics
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _report import write_section  # noqa: E402


def _time(f, args, repeats):
    out = f(*args)
    out.block_until_ready()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f(*args).block_until_ready()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def per_fusion(repeats: int, steps: int = 100_000):
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    Ws = jnp.asarray(rng.normal(0, 0.3, (20, 8, 8)))
    rows = []
    for K in (5, 10, 20):
        def body(x, _, K=K):
            for k in range(K):
                x = jnp.tanh(jnp.sum(x[:, None] * Ws[k], 0)) + 0.01
            return x, None

        f = jax.jit(lambda x, body=body: jax.lax.scan(body, x, None, length=steps)[0])
        x = jnp.linspace(0.0, 1.0, 8)
        n_fus = len(re.findall(r"= \S+ fusion\(", f.lower(x).compile().as_text()))
        rows.append((K, n_fus, _time(f, (x,), repeats) / steps * 1e9))
    ks = np.array([r[0] for r in rows], float)
    ns = np.array([r[2] for r in rows])
    slope = float(np.polyfit(ks, ns, 1)[0])
    return rows, slope


def model_fusions() -> int:
    """Fusions in the loop body of the compiled M3 single-sequence rollout (RK4, dt = 1 s)."""
    import jax.numpy as jnp

    sys.path.insert(0, str(HERE.parent))
    import tnn_dsl

    model = tnn_dsl.compile(tnn_dsl.load(HERE.parent / "networks" / "peltier_heatpipe" / "m3.thn"), "jax")
    p = model.init_params(0)
    T0 = jnp.full((len(model.state_names),), 300.0)
    U = jnp.ones((200, len(model.input_names))) * 300.0
    txt = model._jitted("rollout", 1.0, "rk4", 1).lower(p, T0, U).compile().as_text()
    comps = re.split(r"\n(?=\S)", txt)
    # the loop body is the non-entry computation with the most fusions (the entry holds the work outside the loop)
    return max(len(re.findall(r"= \S+ fusion\(", c)) for c in comps if not c.startswith("ENTRY"))


def model_ladder(repeats: int, steps: int = 20_000, B: int = 256, N: int = 390):
    """The model's own JAX rollout of the case-study models M1 (constant heat-pipe resistances), M2 (linear)
    and M3 (MLP heat pipe): fusions in the compiled loop body, µs/step of a single sequence and µs per
    window-step of a batch — how much of M3's cost is the network and how much the learned function."""
    import jax.numpy as jnp

    sys.path.insert(0, str(HERE.parent))
    from bench_rollout import case_inputs, random_weights

    import tnn_dsl

    rows = []
    for name in ("m1", "m2", "m3"):
        net = tnn_dsl.load(HERE.parent / "networks" / "peltier_heatpipe" / f"{name}.thn")
        ref = tnn_dsl.compile(net, "numpy")
        model = tnn_dsl.compile(net, "jax")
        P = random_weights(ref, 0)
        p = model.from_numpy(P)
        U = case_inputs(ref, max(steps, N * 2), 1.0, 0)
        T0 = ref.steady_state(P, U[0])
        f = model._jitted("rollout", 1.0, "rk4", 1)
        txt = f.lower(p, jnp.asarray(T0), jnp.asarray(U[:steps])).compile().as_text()
        comps = re.split(r"\n(?=\S)", txt)
        n_fus = max(len(re.findall(r"= \S+ fusion\(", c)) for c in comps if not c.startswith("ENTRY"))
        single = _time(lambda a, b: f(p, a, b)[0], (jnp.asarray(T0), jnp.asarray(U[:steps])), repeats) / steps
        starts = np.arange(B) * N % (len(U) - N + 1)
        Ub = jnp.asarray(np.stack([U[s:s + N] for s in starts]))
        T0b = jnp.asarray(T0 + np.random.default_rng(1).normal(0, 0.5, (B, len(T0))))
        batch = _time(lambda a, b: f(p, a, b)[0], (T0b, Ub), repeats) / (B * N)
        rows.append((name, n_fus, single * 1e6, batch * 1e6))
    return rows


def skeleton(repeats: int, B: int = 256, N: int = 390):
    import jax
    import jax.numpy as jnp

    rng = np.random.default_rng(0)
    n = 7
    W0, b0 = jnp.asarray(rng.normal(0, .5, (4, 8))), jnp.asarray(rng.normal(0, .1, 8))
    W1, b1 = jnp.asarray(rng.normal(0, .5, (8, 8))), jnp.asarray(rng.normal(0, .1, 8))
    W2, b2 = jnp.asarray(rng.normal(0, .5, (8, 3))), jnp.asarray(rng.normal(0, .1, 3))
    A = jnp.asarray(rng.normal(0, 1e-3, (n, n)))
    Win = jnp.asarray(rng.normal(0, 1e-3, (n, 3)))
    sel = np.array([3, 4, 5])

    def sig(x):
        return 0.5 + 0.5 * jnp.tanh(0.5 * x)

    def lead(T, u, trans):  # batch leading: T (B, n), u (B, 3)
        x = jnp.concatenate([T[:, sel] - 300.0, u[:, :1]], axis=1) * 0.1
        act = sig if trans else (lambda v: 0.5 + 0.1 * v)
        h = act(x @ W0 + b0)
        h = act(h @ W1 + b1)
        z = h @ W2 + b2
        R = 0.2 * (jax.nn.softplus(4 * (1 + z)) if trans else jnp.maximum(4 * (1 + z), 0.1))
        return T @ A + u @ Win.T + (1 / R) @ Win.T * 1e-3

    def trail(T, u, trans):  # batch trailing: T (n, B), u (3, B)
        x = jnp.concatenate([T[sel] - 300.0, u[:1]], axis=0) * 0.1
        act = sig if trans else (lambda v: 0.5 + 0.1 * v)
        h = act(W0.T @ x + b0[:, None])
        h = act(W1.T @ h + b1[:, None])
        z = W2.T @ h + b2[:, None]
        R = 0.2 * (jax.nn.softplus(4 * (1 + z)) if trans else jnp.maximum(4 * (1 + z), 0.1))
        return A.T @ T + Win @ u + Win @ (1 / R) * 1e-3

    def roll(f, T0, U, trans):
        def body(T, u):
            k1 = f(T, u, trans)
            k2 = f(T + 0.5 * k1, u, trans)
            k3 = f(T + 0.5 * k2, u, trans)
            k4 = f(T + k3, u, trans)
            Tn = T + (k1 + 2 * k2 + 2 * k3 + k4) / 6.0
            return Tn, Tn
        return jax.lax.scan(body, T0, U)[1]

    T0 = jnp.asarray(300 + rng.normal(0, 1, (B, n)))
    U = jnp.asarray(rng.uniform(0, 1, (N, B, 3)))
    rows = []
    for layout, f, args in (("batch leading (the model's)", lead, (T0, U)),
                            ("batch trailing", trail, (T0.T, jnp.moveaxis(U, 1, 2)))):
        for trans in (True, False):
            g = jax.jit(lambda a, b, f=f, trans=trans: roll(f, a, b, trans))
            rows.append((layout, trans, _time(g, args, repeats) / (N * B) * 1e6))
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="a few seconds' worth (shorter loops, 2 repeats)")
    ap.add_argument("--output", default=str(HERE.parent / "BENCHMARKS.md"))
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)
    if args.quick:
        args.repeats = min(args.repeats, 2)
    fus, slope = per_fusion(args.repeats, steps=20_000 if args.quick else 100_000)
    n_model = model_fusions()
    sk = skeleton(args.repeats, N=100 if args.quick else 390)
    ladder = model_ladder(args.repeats, steps=2_000 if args.quick else 20_000, N=50 if args.quick else 390)
    md = ["Per-kernel cost in a `lax.scan` body (chain of K dependent tanh layers on an 8-vector):", "",
          "| layers K | fusions in the compiled loop | ns per step |", "|---|---|---|"]
    md += [f"| {k} | {nf} | {ns:.0f} |" for k, nf, ns in fus]
    md += ["", f"Slope: **{slope:.0f} ns per fusion** in the loop body. The model's compiled RK4 step of the case "
           f"study (M3, single sequence) has {n_model} fusions in its loop body: "
           f"**{n_model * slope / 1000:.2f} µs/step** from kernel cost alone.", "",
           "Skeleton of the batched M3 step (256 windows × 390 steps, RK4; MLP 4→8→8→3 and the network as small "
           "products), µs per window-step:", "",
           "| layout | with transcendentals (tanh-sigmoid, softplus) | µs per window-step |", "|---|---|---|"]
    md += [f"| {lay} | {'yes' if tr else 'no (affine stand-ins)'} | {us:.3f} |" for lay, tr, us in sk]
    floor = min(us for _, tr, us in sk if not tr)
    md += ["", f"Without any transcendental function the skeleton costs at least **{floor:.3f} µs per window-step** "
           "with XLA here."]
    md += ["", "The model's own JAX rollout (RK4, dt = 1 s, float64) of the case-study models, random non-zero learned "
           "weights: heat-pipe resistances learned as constants (M1), as linear functions of three temperatures "
           "and u1 (M2), by the 4→8→8→3 sigmoid MLP (M3):", "",
           "| model | fusions in the loop body | single sequence µs/step | batch of 256, µs per window-step |",
           "|---|---|---|---|"]
    md += [f"| {name.upper()} | {nf} | {s1:.2f} | {b1:.3f} |" for name, nf, s1, b1 in ladder]
    text = "\n".join(md) + "\n"
    print(text)
    if not args.no_write:
        write_section("xla-floor", text, path=args.output,
                      title="XLA's floor on this CPU (issue 3's absolute targets)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
