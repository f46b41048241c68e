"""Maximum-likelihood fits of Bacher & Madsen's building models (issue 16) against CTSM-R's log-likelihoods.

``tnn_dsl.estimation.fit_ml`` (JAX, rk4, L-BFGS-B from the values written in the ``.thn`` files, σ_v = 0.1 K,
σ_w = 1e-3 K/√s, one restart, one more start when a parameter ends at a bound, Hessian by Richardson-extrapolated
differences of the gradient) on ``../shared/data/bacher_madsen_inputPRBS1.csv`` (1691 × 5 min). References:
the maximum log-likelihoods of Bacher & Madsen (2011) / CTSM-R's examples — Ti 2479.2, TiTe 3286.6 (not checked
here), TiTh 3904.7, TiTeTh 5437.0. Printed: log L, its reference, the difference, the number of estimates
without a standard error (at a bound or not identifiable), and the wall time (compilation included).

Measured 2026-11-24 with ``python benchmarks/bench_ml_buildings.py`` (2 shared cores, load average ~3, compilation
included): ti 2479.23 (+0.03, 3.3 s), tith 3904.74 (+0.04, 7.7 s), titeth 5437.12 (+0.12, 12.2 s). Before the
linearisation was formed once per evaluation and the Hessian taken from gradient differences: 7.3 / 18.9 / 22.2 s
(compiling ``jax.hessian`` took 4.5 / 9.2 / 11.1 s of it). TiTeTh stopped at 5431.00 while the filter's mean took
one RK4 step per 5-min sample (stable for the heater node's τ = 360 s, not accurate); with sub-steps of at most
half the fastest time constant (2 here) it reaches 5437.12, with 4 and 8 sub-steps 5437.42 and 5437.43.

    python benchmarks/bench_ml_buildings.py            # ti, tith, titeth, with every summary
    python benchmarks/bench_ml_buildings.py --quick    # ti and tith, the table only
    python benchmarks/bench_ml_buildings.py --backend torch --quick          # the same fits on torch
    python benchmarks/bench_ml_buildings.py --evaluation   # one −log L + gradient per model and backend

``--evaluation`` times one evaluation of −log L and its gradient over the whole file at the written values (the
median of three after a first call that compiles), JAX and torch, with the linearisation of these linear models
formed once per evaluation (the default) and per sample (``likelihood._HOIST = False``, torch's only form before
2026-12-04).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import tnn_dsl
from tnn_dsl.data import read_data
from tnn_dsl.estimation.ml_fit import fit_ml

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "bacher_madsen_inputPRBS1.csv"
if not DATA.exists():
    DATA = Path("/work/shared/data/bacher_madsen_inputPRBS1.csv")
REFERENCE = {"ti": 2479.2, "tith": 3904.7, "titeth": 5437.0}


def evaluation(names: list[str]) -> None:
    """One −log L + gradient per model, backend and form of the linearisation: ms (median of three, warm)."""
    import statistics

    import numpy as np

    from tnn_dsl.estimation import likelihood as lk

    print(f"{'model':<8} {'backend':<7} {'once, ms':>9} {'per sample, ms':>15} {'ratio':>6} {'|Δ −log L|':>11}")
    for name in names:
        net = tnn_dsl.load(ROOT / "networks" / "building" / f"{name}.thn")
        (exp,) = read_data(net, DATA, time_unit="h")
        for backend in ("jax", "torch"):
            model = tnn_dsl.compile(net, backend)
            ms, vals = [], []
            for hoist in (True, False):
                lk._HOIST = hoist
                try:
                    pr = lk.LikelihoodProblem(model, model.init_params(), exp.inputs, exp.outputs, exp.dt,
                                              log_sigma_w=np.log(1e-3), log_sigma_v=np.log(0.1))
                    v, _ = pr.value_and_grad(pr.z0)  # compiles (JAX)
                    times = []
                    for _ in range(3):
                        t0 = time.perf_counter()
                        pr.value_and_grad(pr.z0)
                        times.append(time.perf_counter() - t0)
                finally:
                    lk._HOIST = True
                ms.append(1e3 * statistics.median(times))
                vals.append(v)
            gap = abs(vals[0] - vals[1])
            print(f"{name:<8} {backend:<7} {ms[0]:9.1f} {ms[1]:15.1f} {ms[1] / ms[0]:6.1f} {gap:11.2g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="ti and tith only, no summaries")
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--evaluation", action="store_true",
                    help="time one −log L + gradient per model and backend instead of fitting")
    args = ap.parse_args()
    names = ["ti", "tith"] if args.quick else ["ti", "tith", "titeth"]
    if args.evaluation:
        evaluation(names)
        return
    rows = []
    for name in names:
        net = tnn_dsl.load(ROOT / "networks" / "building" / f"{name}.thn")
        (exp,) = read_data(net, DATA, time_unit="h")
        t0 = time.perf_counter()
        r = fit_ml(net, exp, backend=args.backend)
        took = time.perf_counter() - t0
        if not args.quick:
            print(r.summary(), "\n")
        nose = sum(row["status"] != "ok" for row in r.rows)
        rows.append((name, r.loglik, REFERENCE[name], r.loglik - REFERENCE[name], r.n_params, nose, took))
    print(f"{'model':<8} {'log L':>10} {'CTSM-R':>9} {'diff':>8} {'k':>3} {'no se':>6} {'time s':>7}")
    for name, ll, ref, d, k, nose, took in rows:
        print(f"{name:<8} {ll:10.2f} {ref:9.1f} {d:8.2f} {k:3d} {nose:6d} {took:7.1f}")


if __name__ == "__main__":
    main()
