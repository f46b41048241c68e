"""Time of one initial-state estimate (``--init estimate``: Gauss–Newton on a burn-in) on the case study's
validation file, per backend — the cost every validation of a training run pays.

    python benchmarks/bench_burn_in.py [--net networks/peltier_heatpipe/m2.thn] [--repeats 3]

Prints, per backend (JAX, torch eager, torch with ``torch_compile=True``), the first call (with compilation) and
the median of the later calls, and how far each estimate lies from JAX's (K). Nothing is written."""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--net", default=str(ROOT / "networks" / "peltier_heatpipe" / "m2.thn"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--backends", default="jax,torch-compiled,torch")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "tnn_bench_train_cs"))
    args = ap.parse_args(argv)

    import numpy as np

    import tnn_dsl
    from tnn_dsl.data import as_experiments
    from tnn_dsl.fit.initial import initial_state
    from tnn_dsl.studies.casestudy import generate_case_study

    cs = generate_case_study(args.cache, n_ood=0, widen=(), durations=None)
    net = tnn_dsl.load(args.net)
    exps = as_experiments(net, cs["val"])
    exp = exps[0] if isinstance(exps, list) else exps
    ref = None
    print(f"{Path(args.net).name} on {Path(exp.path or exp.name).name} ({len(exp.t)} samples)")
    for name in args.backends.split(","):
        kw = {"jax": dict(backend="jax"), "torch": dict(backend="torch"),
              "torch-compiled": dict(backend="torch", torch_compile=True)}[name]
        model = tnn_dsl.compile(net, **kw)
        p = model.init_params(0)
        t = time.perf_counter()
        ini = initial_state(net, model, p, exp, "estimate")
        first = time.perf_counter() - t
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            ini = initial_state(net, model, p, exp, "estimate")
            times.append(time.perf_counter() - t)
        ref = ini.T if ref is None else ref
        print(f"{name:15s} first call {first:7.2f} s   then {statistics.median(times):7.3f} s (median of "
              f"{args.repeats})   max |T0 - first backend's| {float(np.max(np.abs(ini.T - ref))):.2g} K", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
