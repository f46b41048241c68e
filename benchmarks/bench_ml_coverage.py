"""Monte-Carlo coverage of the maximum-likelihood standard errors (issue 16: the 95 % intervals of
``tnn_dsl.estimation.fit_ml`` cover the truth 85–100 % of the time over ≥ 50 refits of a small network).

A one-node linear network (C = 130 J/K, R = 0.4 K/W, σ_w = 0.03 K/√s, σ_v = 0.08 K, x0 = 296 K) is simulated
exactly (numpy; ``T⁺ = T∞ + a(T − T∞) + w``, ``a = e^{−Δt/τ}``, ``w ~ N(0, σ_w² τ (1 − a²)/2)``, readings with
N(0, σ_v²) noise; Δt = 5 s, a sine ambient and a power stepped every 15 samples), one record per seed, and
refitted (``integrator="expeuler"``, exact for this network). Each estimate's 95 % interval is the Wald
interval in the fitted coordinate (``z ± 1.96·se_z``: log space for C, R, σ_w, σ_v — i.e. ``value·e^{±1.96 se_z}``
— and linear for x0). Printed: coverage per parameter and pooled, and the time per refit.

    python benchmarks/bench_ml_coverage.py            # 50 refits of 300 samples
    python benchmarks/bench_ml_coverage.py --quick    # 10 refits
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

import tnn_dsl
from tnn_dsl.estimation.ml_fit import fit_ml

RC = """
network rc "one node"
units temperature = K
input Ta : temperature column "Ta"
input P  : [W] column "P"
boundary amb = Ta
node n C = 100 J/K  free in [1 J/K, 10000 J/K]
R n -- amb = 0.5 K/W  free in [0.01 K/W, 50 K/W] as Rn
source n = P
sensor y = n column "y"
"""

TRUTH = {"C_n": 130.0, "Rn": 0.4, "sigma_w[n]": 0.03, "sigma_v[y]": 0.08, "x0[n]": 296.0}


def simulate(N: int, dt: float = 5.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Exact simulation of ``C dT = ((Ta − T)/R + P) dt + C·σ_w dω`` in the likelihood's convention
    ``dT = f dt + σ_w dω``: ``T⁺ = T∞ + a (T − T∞) + w``, ``a = e^{−Δt/τ}``, ``w ~ N(0, σ_w² τ (1 − a²)/2)``,
    inputs held over the sample; readings ``T + N(0, σ_v²)``. Returns inputs ``(N, 2)`` [Ta K, P W] and readings
    ``(N, 1)`` K. (Also the fixture of tests/test_ml_fit.py.)"""
    rng = np.random.default_rng(seed)
    C, R, sw, sv = TRUTH["C_n"], TRUTH["Rn"], TRUTH["sigma_w[n]"], TRUTH["sigma_v[y]"]
    tau = R * C
    a = math.exp(-dt / tau)
    q = sw ** 2 * tau * (1 - a * a) / 2
    Ta = 293.0 + 2.0 * np.sin(np.arange(N) / 40.0)
    P = np.repeat(rng.uniform(0.0, 20.0, N // 15 + 1), 15)[:N]
    x = TRUTH["x0[n]"]
    y = np.empty(N)
    for k in range(N):
        y[k] = x + sv * rng.standard_normal()
        xinf = Ta[k] + R * P[k]
        x = xinf + a * (x - xinf) + math.sqrt(q) * rng.standard_normal()
    return np.stack([Ta, P], axis=1), y[:, None]


def coverage(n_refits: int, N: int = 300, dt: float = 5.0, seed0: int = 1000, model=None) -> dict:
    """``{"per_param": {name: fraction}, "pooled": fraction, "hits": int, "intervals": int, "seconds": float,
    "failed": int}`` over ``n_refits`` simulated records (``model``: a compiled :data:`RC` to reuse)."""
    model = model if model is not None else tnn_dsl.compile(tnn_dsl.loads(RC, "rc.thn"), "jax")
    hits = {k: 0 for k in TRUTH}
    counted = {k: 0 for k in TRUTH}
    failed = 0
    t0 = time.perf_counter()
    for i in range(n_refits):
        U, Y = simulate(N, dt, seed0 + i)
        r = fit_ml(model, (U, Y, dt), integrator="expeuler")
        for row in r.rows:
            if row["status"] != "ok":
                failed += 1
                continue
            truth = TRUTH[row["name"]]
            zt = math.log(truth) if row["coordinate"] == "log" else truth - (row["estimate"] - row["z"])
            counted[row["name"]] += 1
            hits[row["name"]] += abs(row["z"] - zt) <= 1.96 * row["se_z"]
    total_h, total_n = sum(hits.values()), sum(counted.values()) + failed
    return {"per_param": {k: hits[k] / max(counted[k], 1) for k in TRUTH}, "pooled": total_h / max(total_n, 1),
            "hits": total_h, "intervals": total_n, "failed": failed, "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 refits instead of 50")
    ap.add_argument("--refits", type=int, default=None)
    ap.add_argument("--samples", type=int, default=300)
    args = ap.parse_args()
    n = args.refits or (10 if args.quick else 50)
    res = coverage(n, args.samples)
    print(f"95 % Wald intervals over {n} refits of {args.samples} samples ({res['seconds']:.1f} s, "
          f"{res['seconds'] / n:.2f} s a refit)")
    print(f"{'parameter':<12} {'coverage':>9}")
    for k, v in res["per_param"].items():
        print(f"{k:<12} {100 * v:8.1f} %")
    print(f"{'pooled':<12} {100 * res['pooled']:8.1f} %  ({res['hits']}/{res['intervals']}; "
          f"{res['failed']} without a standard error, counted as misses)")


if __name__ == "__main__":
    main()
