"""Run every benchmark in ``benchmarks/`` (``make bench``).

Discovers ``benchmarks/bench_*.py`` and ``benchmarks/*_suite.py`` and runs each as its own subprocess
(one at a time: the benchmarks time things, so they must not compete for the cores), forwarding
``--quick`` when given. Each script writes its own section of ``BENCHMARKS.md`` through
``benchmarks/_report.py``. Exits non-zero if any script failed; prints a one-line summary per script.

    python benchmarks/run_all.py                 # everything, full size
    python benchmarks/run_all.py --quick         # each script's quick mode
    python benchmarks/run_all.py --only rollout  # scripts whose file name contains "rollout"
    python benchmarks/run_all.py --list
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def discover(directory: Path = HERE) -> list[Path]:
    """The benchmark scripts in ``directory``, sorted by name (helpers starting with ``_`` excluded)."""
    found = set(directory.glob("bench_*.py")) | set(directory.glob("*_suite.py"))
    return sorted(p for p in found if not p.name.startswith("_") and p.name != Path(__file__).name)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Run every benchmark script (make bench).")
    ap.add_argument("--quick", action="store_true", help="pass --quick to every script (short runs)")
    ap.add_argument("--only", action="append", default=[], metavar="TEXT",
                    help="run only scripts whose file name contains TEXT (repeatable)")
    ap.add_argument("--list", action="store_true", help="list the scripts and exit")
    ap.add_argument("--timeout", type=float, default=None, help="seconds allowed per script (default: none)")
    args, extra = ap.parse_known_args(argv)
    scripts = discover()
    if args.only:
        scripts = [s for s in scripts if any(t in s.name for t in args.only)]
    if args.list:
        for s in scripts:
            print(s.relative_to(HERE.parent))
        return 0
    if not scripts:
        print("run_all: no benchmark scripts found" + (f" matching {args.only}" if args.only else ""), file=sys.stderr)
        return 1
    failed = []
    summary = []
    for script in scripts:
        cmd = [sys.executable, str(script), *(["--quick"] if args.quick else []), *extra]
        print(f"==> {' '.join(cmd)}", flush=True)
        t = time.perf_counter()
        try:
            rc = subprocess.run(cmd, cwd=HERE.parent, timeout=args.timeout).returncode
        except subprocess.TimeoutExpired:
            rc = "timeout"
        dt = time.perf_counter() - t
        ok = rc == 0
        summary.append(f"{'ok  ' if ok else 'FAIL'} {script.name} ({dt:.0f} s" + ("" if ok else f", exit {rc}") + ")")
        if not ok:
            failed.append(script.name)
    print("\n".join(["", "benchmarks:", *("  " + s for s in summary)]))
    if failed:
        print(f"run_all: {len(failed)} benchmark(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
