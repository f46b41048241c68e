"""Where the torch demo's compiling goes (issue 18): runs ``tnnc demo`` in this process with the arguments given and
prints, at the end, torch's own account of its compilations (``torch._dynamo.utils.compile_times``: dynamo's
tracing, AOT autograd, inductor's passes, lowering, scheduling and code generation, the C++ compiler — seconds
summed over every graph the process compiled) and its cache counters (inductor's FX graph cache and AOT
autograd's: hits, misses, bypasses).

    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) python benchmarks/profile_demo_compile.py --backend torch \
        --no-diagnose --out DIR

``TNN_COMPILE_AHEAD=0`` in front compiles every model in this process (no helper process,
``tnn_dsl.fit.compile_ahead``). Nothing is written but the demo's own ``--out``."""

from __future__ import annotations

import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    import torch._dynamo.utils as dynamo_utils

    from tnn_dsl.cli import main as tnnc

    t0 = time.perf_counter()
    rc = tnnc(["demo", *(sys.argv[1:] if argv is None else argv)])
    print(f"\nwall {time.perf_counter() - t0:.1f} s (exit {rc})")
    print(dynamo_utils.compile_times(repr="str", aggregate=True))
    counters = dynamo_utils.counters
    for group in ("inductor", "aot_autograd"):
        keep = {k: v for k, v in counters[group].items() if "cache" in k}
        print(f"{group} cache counters: {keep or 'none'}")
    return int(rc or 0)


if __name__ == "__main__":
    raise SystemExit(main())
