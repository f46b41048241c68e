"""Where the diagnosis' memory goes (issue 18): ``tnnc diagnose`` of the case study from M1 (as
``bench_diagnose.py``) with every engine call of the score test and the fits wrapped to print the resident size
before, after and at its highest during the call (``/proc/self/status``; the high-water mark reset per call through
``/proc/self/clear_refs``), stopped after the score test of round ``--rounds``; one candidate fit at a time
unless ``TNN_DOCTOR_THREADS`` says otherwise. Linux only.

    python benchmarks/trace_diagnose_memory.py                           # as shipped: 16 tangents, heap trimmed
    python benchmarks/trace_diagnose_memory.py --chunk 32 --no-release   # as before issue 18's memory changes

Prints one line per call and a last line with the highest resident size seen; nothing is written.
"""

from __future__ import annotations

import argparse
import functools
import os
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

T0 = time.perf_counter()
PEAK = [0]


def _mem() -> dict[str, int]:
    out = {}
    with open("/proc/self/status", encoding="ascii") as f:
        for line in f:
            if line.startswith(("VmRSS", "VmHWM")):
                k, v = line.split(":")
                out[k] = int(v.split()[0]) // 1024
    return out


def _reset_high_water() -> None:
    with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
        f.write("5")


def _traced(fn, name: str):
    @functools.wraps(fn)
    def call(*a, **k):
        m0 = _mem()
        _reset_high_water()
        t = time.perf_counter()
        out = fn(*a, **k)
        dt = time.perf_counter() - t
        m1 = _mem()
        PEAK[0] = max(PEAK[0], m1["VmHWM"])
        print(f"[{time.perf_counter() - T0:6.1f} s] {name:20s} {dt:6.2f} s  RSS {m0['VmRSS']:5d} -> "
              f"{m1['VmRSS']:5d} MB, highest in the call {m1['VmHWM']:5d} MB", flush=True)
        return out

    return call


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=2, help="stop after this round's score test")
    ap.add_argument("--chunk", type=int, default=None, help="score-test tangents per batch (default: shipped)")
    ap.add_argument("--no-release", action="store_true", help="do not hand the heap's free pages back")
    ap.add_argument("--dir", default=None, help="where the case study is generated (default: a temporary folder)")
    args = ap.parse_args(argv)
    os.environ.setdefault("TNN_DOCTOR_THREADS", "1")  # one fit at a time: each call's memory is its own

    from tnn_dsl.doctor import diagnosis, engine, scoring, session, threads
    from tnn_dsl.studies.casestudy import generate_case_study

    if args.chunk:
        scoring.FORCED_CHUNK = args.chunk
    if args.no_release:
        for mod in (scoring, session, threads, diagnosis):
            mod.release_free_memory = lambda: False
    for name in ("point_derivs", "forced_jacobian", "jacobian", "inv_capacity", "rates", "fit"):
        setattr(engine._Engine, name, _traced(getattr(engine._Engine, name), name))
    for name in ("_structural_columns", "_score_stats"):  # the structural forcings are a generator since 4ef79bb
        setattr(scoring, name, _traced(getattr(scoring, name), name))
    score = session._Session.score

    def score_then_stop(self, rnd):
        out = score(self, rnd)
        print(f"=== round {rnd} score test done", flush=True)
        if rnd >= args.rounds:
            print(f"highest resident size seen: {PEAK[0]} MB ({time.perf_counter() - T0:.0f} s)", flush=True)
            sys.stdout.flush()
            os._exit(0)
        return out

    session._Session.score = score_then_stop
    tmp = tempfile.TemporaryDirectory(prefix="tnn-trace-")
    data = Path(args.dir) if args.dir else Path(tmp.name)
    if not (data / "train.csv").is_file():
        generate_case_study(data, widen=(), n_ood=0)
    from tnn_dsl.cli import main as tnnc

    return tnnc(["diagnose", str(ROOT / "networks" / "peltier_heatpipe" / "m1.thn"), str(data / "train.csv"),
                 "--val", str(data / "val.csv"), "--backend", "jax"])


if __name__ == "__main__":
    sys.exit(main())
