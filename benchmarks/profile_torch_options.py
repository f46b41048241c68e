"""Inductor options for the compiled adjoint scans, tried on one training step (issue 18): the case study's M2 on
24 windows × 601 samples (dt 1 s, RK4, float64), forward with gradients and the backward pass, with a set of
``torch.compile`` options added to the model's own (``compiler.model.inductor_options``). Prints one JSON line:
the first call (tracing and compiling both scans, into the inductor cache the environment names) and the median
and fastest of 15 further calls.

    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python benchmarks/profile_torch_options.py '{}'
    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python benchmarks/profile_torch_options.py \\
        '{"aot_inductor.compile_wrapper_opt_level": "O0"}'

Compare options one after the other, each in a fresh cache directory (the host's speed drifts). A profiling tool,
not part of ``make bench`` (it writes no section of BENCHMARKS.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("options", nargs="?", default="{}",
                    help='inductor options as a JSON object, e.g. \'{"memory_planning": true}\' (default: none)')
    opts = json.loads(ap.parse_args(argv).options)
    import torch

    import tnn_dsl
    from tnn_dsl.compiler import compile as compile_network
    from tnn_dsl.compiler import model as compiled_model

    torch.set_num_threads(1)
    base = compiled_model.inductor_options
    compiled_model.inductor_options = lambda: {**base(), **opts}
    m = compile_network(tnn_dsl.load(ROOT / "networks" / "peltier_heatpipe" / "m2.thn"), backend="torch",
                        torch_compile=True)
    p = {k: v.detach().clone().requires_grad_(v.dtype.is_floating_point) if torch.is_tensor(v) else v
         for k, v in m.init_params(seed=0).items()}
    wrt = [v for v in p.values() if torch.is_tensor(v) and v.requires_grad]
    g = torch.Generator().manual_seed(0)
    T0 = 300 + torch.rand(24, len(m.state_names), generator=g, dtype=torch.float64)
    U = torch.rand(24, 601, len(m.input_names), generator=g, dtype=torch.float64)

    def step():
        _S, Y = m.rollout(p, T0, U, 1.0)
        return torch.autograd.grad((Y ** 2).sum(), wrt)

    t = time.perf_counter()
    step()
    first = time.perf_counter() - t
    times = []
    for _ in range(15):
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    times.sort()
    print(json.dumps({"options": opts, "first_call_s": round(first, 2), "call_ms_median": round(1e3 * times[7], 1),
                      "call_ms_min": round(1e3 * times[0], 1)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
