"""Many parameter sets over one input sequence on compiled torch (issue 18; ``Model.rollouts_of``, the model doctor's
difference Jacobians): the vmapped compiled scan against one compiled rollout per set, per set and chunk size.

    python benchmarks/profile_param_batch.py                       # case study M1, 14 401 samples, chunks 4 8 16
    python benchmarks/profile_param_batch.py --sizes 8 --samples 9600

Random inputs in the case study's ranges and the network's initial values scaled by 1 + 0.001·k for set k; each
chunk size compiles its own graph (the time printed apart), then the best of three calls of one chunk of that size.
Nothing is written."""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--network", default=str(ROOT / "networks" / "peltier_heatpipe" / "m1.thn"))
    ap.add_argument("--samples", type=int, default=14_401)
    ap.add_argument("--sizes", type=int, nargs="+", default=[4, 8, 16])
    a = ap.parse_args(argv)

    import numpy as np
    import torch

    import tnn_dsl
    import tnn_dsl.compiler.model as M

    warnings.simplefilter("ignore", UserWarning)
    net = tnn_dsl.load(a.network)
    m = tnn_dsl.compile(net, "torch", torch_compile=True)
    rng = np.random.default_rng(0)
    p0 = {k: v.detach().numpy() for k, v in m.init_params(0).items()}
    ns = len(m.state_names)
    temp = np.array([n.startswith("T") for n in m.input_names])
    U = torch.as_tensor(0.5 + 0.5 * rng.random((a.samples, len(m.input_names))) + 295.0 * temp)

    def sets(B):
        return ([{k: torch.as_tensor(v * (1 + 1e-3 * b)) for k, v in p0.items()} for b in range(B)],
                torch.as_tensor(298.0 + rng.random((B, ns))))

    def best(f, n=3):
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return min(ts)

    ps, T0 = sets(1)
    with torch.no_grad():
        t = time.perf_counter()
        m.rollout(ps[0], T0[0], U, 1.0)
        c1 = time.perf_counter() - t
        one = best(lambda: m.rollout(ps[0], T0[0], U, 1.0))
    print(f"{net.name}, {a.samples} samples: one compiled rollout {1e3 * one:.1f} ms (first call {c1:.1f} s)")
    for B in a.sizes:
        M.TORCH_PARAM_BATCH = B
        ps, T0 = sets(B)
        with torch.no_grad():
            t = time.perf_counter()
            m.rollouts_of(ps, T0, U, 1.0)
            c = time.perf_counter() - t
            run = best(lambda: m.rollouts_of(ps, T0, U, 1.0))
        print(f"chunk of {B:3d}: {1e3 * run:8.1f} ms, {1e3 * run / B:6.1f} ms a set ({one / (run / B):.1f}x one "
              f"rollout each); first call {c:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
