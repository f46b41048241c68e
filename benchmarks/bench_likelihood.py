"""The Kalman-filter likelihood on both backends (issue 18: torch at JAX's speed): one evaluation of ``−log L`` and
its gradient (``LikelihoodProblem.value_and_grad``), and a whole maximum-likelihood fit (``fit_ml``).

Two networks, each simulated here (seeded) and filtered as written:

* ``rc``: one node, linear (``benchmarks/bench_ml_coverage.py``'s network and exact simulator, Δt = 20 s): its
  linearisation is constant, so the filter forms ``H``, ``F`` and ``Q_d`` once per evaluation;
* ``tclab_lag``: ``networks/tclab/tclab_lag.thn`` (two heaters, two sensor lags, radiation in absolute
  temperature), Δt = 1 s, its heaters stepped every 60 samples, 0.05 K of sensor noise: its linearisation
  depends on the state, so the filter differentiates the step at every sample.

JAX's times are after its compilation (reported apart); torch runs eager. Printed and written to BENCHMARKS.md:
ms per evaluation and per sample, and the ratio torch / JAX.

A third table (not with ``--quick``): real data, a long record, a constant linearisation — Bacher & Madsen's Ti with
a heat capacity behind the solar gain (``bench_ml_diverged_start.py``'s network; ``../shared/data/
bacher_madsen_inputPRBS1.csv``, DTU's CTSM-R example, 1691 samples at 5 min), torch's filter as compiled scans (a
fit's default for such a record, ``estimation.torch_filter``; inductor's cache pointed at an empty directory unless
``--warm-torch-cache``), eager (stationary stretches vectorised), eager sample by sample (what eager torch runs
where the covariance does not settle), and JAX.

    python benchmarks/bench_likelihood.py            # 240 samples, 3 repeats, and the RC fit on both backends
    python benchmarks/bench_likelihood.py --quick    # 60 samples, 2 repeats, no fit
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _report import write_section  # noqa: E402
from bench_ml_coverage import RC, simulate  # noqa: E402

import tnn_dsl  # noqa: E402
from tnn_dsl.estimation.likelihood import LikelihoodProblem  # noqa: E402
from tnn_dsl.estimation.ml_fit import fit_ml  # noqa: E402


def _tclab_record(n: int, seed: int = 0) -> tuple:
    net = tnn_dsl.load(HERE.parent / "networks" / "tclab" / "tclab_lag.thn")
    m = tnn_dsl.compile(net, "numpy")
    rng = np.random.default_rng(seed)
    U = np.repeat(rng.uniform(0.0, 80.0, size=(n // 60 + 1, 2)), 60, axis=0)[:n]
    p = m.init_params()
    T0 = np.asarray(m.steady_state(p, U[0]))
    _, Y = m.rollout(p, T0, U, 1.0)
    return net, U, np.asarray(Y) + 0.05 * rng.standard_normal(np.shape(Y)), 1.0


def _rc_record(n: int) -> tuple:
    U, Y = simulate(n, dt=20.0, seed=5)
    return tnn_dsl.loads(RC, "rc.thn"), U, Y, 20.0


def per_evaluation(net, U, Y, dt, backend: str, repeats: int) -> tuple[float, float, bool]:
    """``(compile s, s per value_and_grad, constant linearisation)`` (the first call apart: JAX compiles there)."""
    m = tnn_dsl.compile(net, backend)
    pr = LikelihoodProblem(m, m.init_params(), U, Y, dt)
    t = time.perf_counter()
    pr.value_and_grad(pr.z0)
    first = time.perf_counter() - t
    best = float("inf")
    for i in range(repeats):
        t = time.perf_counter()
        pr.value_and_grad(pr.z0 + 0.01 * (i + 1))
        best = min(best, time.perf_counter() - t)
    return first, best, pr.static.constant


def bacher_madsen_rows(repeats: int) -> list[str]:
    """The third table's rows: ``| filter | first call s | ms / evaluation | / JAX | −log L |``."""
    import os

    from bench_ml_diverged_start import DATA, NETWORK

    from tnn_dsl.estimation import likelihood as lk

    net = tnn_dsl.loads(NETWORK, "q_solar.thn")
    e = tnn_dsl.read_data(net, [str(DATA)])[0]
    U, Y, dt = np.asarray(e.inputs), np.asarray(e.outputs), float(e.dt)
    rows, ref = [], None
    for label, backend, env, stationary in (("JAX", "jax", "", True),
                                            ("torch, compiled scans", "torch", "1", True),
                                            ("torch eager", "torch", "0", True),
                                            ("torch eager, sample by sample", "torch", "0", False)):
        os.environ["TNN_TORCH_COMPILE"] = env
        lk._STATIONARY = stationary
        m = tnn_dsl.compile(net, backend)
        pr = LikelihoodProblem(m, m.init_params(), U, Y, dt)
        t = time.perf_counter()
        v, _ = pr.value_and_grad(pr.z0)
        first = time.perf_counter() - t
        best = float("inf")
        for i in range(repeats if stationary else 1):
            t = time.perf_counter()
            pr.value_and_grad(pr.z0 + 0.01 * (i + 1))
            best = min(best, time.perf_counter() - t)
        ref = best if ref is None else ref
        rows.append(f"| {label} | {first:.2f} | {1e3 * best:.1f} | {best / ref:.1f}× | {v:.10f} |")
        print(rows[-1], flush=True)
    os.environ.pop("TNN_TORCH_COMPILE", None)
    lk._STATIONARY = True
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=int, default=240)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="60 samples, 2 repeats, no fit")
    ap.add_argument("--output", default=str(HERE.parent / "BENCHMARKS.md"))
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--warm-torch-cache", action="store_true",
                    help="keep inductor's on-disk cache (default: an empty one, so compiling is timed cold)")
    args = ap.parse_args(argv)
    import os
    import tempfile

    cold = None if args.warm_torch_cache else tempfile.TemporaryDirectory(prefix="tnn_bench_inductor_")
    if cold is not None:
        os.environ["TORCHINDUCTOR_CACHE_DIR"] = cold.name
    try:
        return _run(args)
    finally:
        if cold is not None:
            cold.cleanup()


def _run(args) -> int:
    import torch

    torch.set_num_threads(1)
    if args.quick:
        args.samples, args.repeats = min(args.samples, 60), min(args.repeats, 2)
    n = args.samples
    md = [f"`LikelihoodProblem.value_and_grad` on {n} samples, best of {args.repeats} (JAX after compiling, torch "
          "eager; one thread):", "",
          "| network | linearisation | JAX compile s | JAX ms / evaluation | torch ms / evaluation | torch ms / sample "
          "| torch / JAX |", "|---|---|---|---|---|---|---|"]
    for name, rec in (("rc", _rc_record(n)), ("tclab_lag", _tclab_record(n))):
        (cj, j, const), (_, t, _) = (per_evaluation(*rec, "jax", args.repeats),
                                     per_evaluation(*rec, "torch", args.repeats))
        md.append(f"| {name} | {'constant' if const else 'per sample'} | {cj:.1f} | {1e3 * j:.2f} | {1e3 * t:.1f} "
                  f"| {1e3 * t / n:.2f} | {t / j:.0f}× |")
        print(md[-1], flush=True)
    if not args.quick:
        net, U, Y, dt = _rc_record(120)
        md += ["", "`fit_ml` of the one-node RC network on 120 samples (L-BFGS-B from the written values, a restart, "
               "the Hessian by central differences; wall time including JAX's compiling):", "",
               "| backend | s | log L |", "|---|---|---|"]
        for backend in ("jax", "torch"):
            t = time.perf_counter()
            r = fit_ml(net, [(U, Y, dt)], backend=backend)
            md.append(f"| {backend} | {time.perf_counter() - t:.1f} | {r.loglik:.6f} |")
            print(md[-1], flush=True)
    if not args.quick:
        md += ["", "Bacher & Madsen's Ti with a heat capacity behind the solar gain (1691 samples, 2 states, 1 "
               f"sensor), `LikelihoodProblem.value_and_grad` at the written values; best of {args.repeats} after the "
               "first call (sample by sample: one call):", "",
               "| filter | first call s | ms / evaluation | / JAX | −log L |", "|---|---|---|---|---|"]
        md += bacher_madsen_rows(args.repeats)
    text = "\n".join(md) + "\n"
    print(text)
    if not args.no_write:
        write_section("likelihood", text, path=args.output,
                      title="The Kalman-filter likelihood on both backends (issue 18)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
