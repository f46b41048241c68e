"""Where the diagnosis' page faults go (issue 18): ``tnn_dsl.diagnose`` of the case study from M1 (the data of
``bench_diagnose.py``, generated into ``--dir`` when missing) in this process, one candidate fit at a time, no MLP
check, with the doctor engine's calls wrapped to count the minor page faults (``ru_minflt``) and the seconds of each
(calls inside a wrapped call count for the outer one). Linux only; prints a table, writes nothing.

    python benchmarks/profile_page_faults.py --dir DIR
    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 python benchmarks/profile_page_faults.py --dir DIR   # as tnnc diagnose runs

A profiling tool, not part of ``make bench``: ``tnnc diagnose`` itself starts again with glibc's huge pages where
they change something (``tnn_dsl.cli.entry``); this script, run directly, only has them when started with the
variable set (``core.memory.huge_pages_environment``).
"""

from __future__ import annotations

import argparse
import collections
import functools
import resource
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CALLS = ("jacobian", "_train_sse", "simulate", "point_derivs", "forced_jacobian", "initial_states")
"""The engine's methods counted (``tnn_dsl.doctor.engine._Engine``)."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dir", default=None, help="the case study's data (bench_diagnose.py's --dir; made if missing)")
    ap.add_argument("--point-block", type=int, default=None,
                    help="samples per call of the score test's pointwise derivatives on JAX (engine.POINT_BLOCK)")
    a = ap.parse_args(argv)
    import tnn_dsl.doctor.engine as engine

    if a.point_block:
        engine.POINT_BLOCK["jax"] = a.point_block
    from tnn_dsl.doctor import diagnose
    from tnn_dsl.studies.casestudy import generate_case_study

    data = (Path(a.dir) if a.dir else Path(tempfile.mkdtemp(prefix="profile_faults_"))) / "cs"
    if not (data / "train.csv").is_file():
        generate_case_study(data, widen=(), n_ood=0)

    def faults() -> int:
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    counts: dict[str, list[float]] = collections.defaultdict(lambda: [0, 0, 0.0])
    inside = [0]

    def counted(fn, name):
        @functools.wraps(fn)
        def call(*args, **kw):
            if inside[0]:
                return fn(*args, **kw)
            inside[0] += 1
            f0, t0 = faults(), time.perf_counter()
            try:
                return fn(*args, **kw)
            finally:
                inside[0] -= 1
                row = counts[name]
                row[0] += 1
                row[1] += faults() - f0
                row[2] += time.perf_counter() - t0
        return call

    for name in CALLS:
        setattr(engine._Engine, name, counted(getattr(engine._Engine, name), name))
    f0, t0 = faults(), time.perf_counter()
    diagnose(str(ROOT / "networks" / "peltier_heatpipe" / "m1.thn"), [str(data / "train.csv")],
             val=[str(data / "val.csv")], threads=1, mlp_check=False, backend="jax", progress=lambda _s: None)
    total_faults, total_s = faults() - f0, time.perf_counter() - t0
    print(f"diagnosis: {total_s:.1f} s, {total_faults / 1e6:.2f} million minor page faults "
          f"(system time {resource.getrusage(resource.RUSAGE_SELF).ru_stime:.1f} s in the whole process)\n")
    print("| engine call | calls | page faults | per call | seconds |")
    print("|---|---|---|---|---|")
    for name, (n, nf, s) in sorted(counts.items(), key=lambda kv: -kv[1][1]):
        print(f"| `{name}` | {n:.0f} | {nf:.0f} | {nf / max(n, 1):.0f} | {s:.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
