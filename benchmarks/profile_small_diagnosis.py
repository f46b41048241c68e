"""Where a small diagnosis' time goes (issue 18): one case of the hidden-effect suite (``diagnose_suite.py``; quick,
0.01 K noise, seed 0, as ``tests/test_diagnose_hidden.py`` runs it), with JAX's compilation events summed and each
compiled program's XLA time by function name; ``--cache`` turns on JAX's persistent compilation cache in a fresh
directory for the run (how many programs repeat).

    python benchmarks/profile_small_diagnosis.py tclab/column_dependence
    XLA_FLAGS=--xla_backend_optimization_level=0 python benchmarks/profile_small_diagnosis.py tclab/column_dependence
    python benchmarks/profile_small_diagnosis.py tclab/column_dependence --cache

Prints the total, the first answer, the compilation sums (and cache hits) and the programs by XLA compile time.
"""

from __future__ import annotations

import argparse
import collections
import logging
import re
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("case", help="a case of diagnose_suite.py, e.g. tclab/column_dependence")
    ap.add_argument("--cache", action="store_true", help="JAX's persistent cache in a fresh directory")
    a = ap.parse_args(argv)

    import jax
    from jax import monitoring

    if a.cache:
        jax.config.update("jax_compilation_cache_dir", tempfile.mkdtemp(prefix="tnn_small_diag_cache_"))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_compilation_cache_max_size", 2**31)  # a limit turns on the file lock
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    counts: collections.Counter = collections.Counter()
    seconds: dict[str, float] = collections.defaultdict(float)

    def on_duration(event: str, s: float, **_kw) -> None:
        if "compile" in event or "cache" in event:
            counts[event] += 1
            seconds[event] += s

    monitoring.register_event_listener(lambda event, **_kw: counts.update([event]) if "cache" in event else None)
    monitoring.register_event_duration_secs_listener(on_duration)
    per_program: dict[str, list] = collections.defaultdict(lambda: [0, 0.0])

    class _Compiles(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            m = re.search(r"Finished XLA compilation of (.*?) in ([0-9.e-]+) sec", record.getMessage())
            if m:
                per_program[m.group(1)][0] += 1
                per_program[m.group(1)][1] += float(m.group(2))

    jax.config.update("jax_log_compiles", True)
    log = logging.getLogger("jax")
    log.addHandler(_Compiles())
    log.setLevel(logging.DEBUG)
    log.propagate = False

    import diagnose_suite as S

    case = {c.name: c for c in S.CASES}[a.case]
    t0 = time.perf_counter()
    r = S.run_case(case, noise=0.01, seed=0, quick=True)
    print(f"total {time.perf_counter() - t0:.1f} s; first answer {r['first_answer']}")
    for event in sorted(counts):
        print(f"{event:55s} {counts[event]:5d} {seconds.get(event, 0.0):7.2f} s")
    for name, (n, s) in sorted(per_program.items(), key=lambda kv: -kv[1][1]):
        print(f"XLA  {name[:50]:50s} {n:5d} {s:7.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
