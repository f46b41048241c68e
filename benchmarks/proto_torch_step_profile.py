"""Where the time of one compiled torch integration step goes (case study M3, RK4, single sequence): the torch
profiler around 200 calls of ``torch.compile`` of one step (the model's per-step path), with inductor's kernel
profiling on, so the fused C++ kernel is timed apart from the call around it (dynamo's cache lookup, the compiled
graph's Python wrapper and buffer allocation). This is why ``torch_compile=True`` runs a forward rollout as one
compiled ``scan`` (``Model._compiled_torch_rollout``) rather than one compiled call per step.

    python benchmarks/proto_torch_step_profile.py

Measured 2026-11-26 (AMD EPYC; BENCHMARKS.md "Rollout cost: reading and proposals"): see that note.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

os.environ.setdefault("TORCHINDUCTOR_CPP_ENABLE_KERNEL_PROFILE", "1")  # before torch is imported

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def main() -> int:
    import bench_rollout as br
    import torch
    from torch.profiler import profile

    import tnn_dsl

    torch.set_num_threads(1)
    case = br.Case(br.parse(["--steps", "200", "--batch", "1", "--slow-steps", "200"]))
    model = tnn_dsl.compile(case.net, "torch")
    prep = model._prepare(model.from_numpy(case.params))
    U = torch.as_tensor(case.U)
    ctx = model._core.rhs_u(prep, U[:-1])
    c0 = {"s": {k: v[0] for k, v in ctx["s"].items()}, "v": {k: v[0] for k, v in ctx["v"].items()}, "u": ctx["u"][0]}
    T0 = torch.as_tensor(case.T0)

    core = model._fused_core()  # built outside the trace (its construction is numpy work)

    def step(prep, T, c):
        return model._stepper(prep, case.dt, case.integrator, case.substeps, core)(T, c)

    compiled = torch.compile(step, fullgraph=True, dynamic=False)
    with torch.no_grad():
        compiled(prep, T0, c0)
        n = 2000
        t = time.perf_counter()
        for _ in range(n):
            compiled(prep, T0, c0)
        print(f"one compiled step call: {(time.perf_counter() - t) / n * 1e6:.1f} µs (wall, {n} calls)")
        with profile() as prof:
            for _ in range(200):
                compiled(prep, T0, c0)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=8))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
