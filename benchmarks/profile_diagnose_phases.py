"""Where the diagnosis leaves the machine's cores idle (issue 18): ``tnnc diagnose`` of the case study from M1 (as
``bench_diagnose.py``: 4 h of training, 2 h held out, the MLP check on) run as a child process, its progress lines
timestamped as they come and its CPU time and resident size sampled from ``/proc`` every ``--every`` s. Prints, for
each stretch between two progress lines of at least ``--min`` s, its start, length, the cores it kept busy on average
(100 % = one) and its highest resident size; then the peak and the wall time. Linux only.

    python benchmarks/profile_diagnose_phases.py --dir /tmp/cs_phases             # this tree
    python benchmarks/profile_diagnose_phases.py --dir /tmp/cs_phases --tree DIR  # another checkout (A/B)

A stretch is named by the line that opens it; lines said together at the end of a batch of side-by-side fits open
stretches of a few milliseconds, which ``--min`` leaves out. Nothing is written but the generated data under ``--dir``
and the diagnosis' JSON there.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PAGE_KB = os.sysconf("SC_PAGE_SIZE") // 1024 if hasattr(os, "sysconf") else 4
TICKS = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _sample(pid: int, every: float, out: list[tuple[float, float, float]], done: threading.Event) -> None:
    """``(time, CPU seconds so far, resident MB)`` of process ``pid`` every ``every`` s until it ends."""
    stat = f"/proc/{pid}/stat"
    while not done.is_set():
        try:
            with open(stat) as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            break
        # after the command's name: state is field 3, utime 14, stime 15, rss 24 (man 5 proc), here shifted by 3
        cpu = (int(fields[11]) + int(fields[12])) / TICKS
        out.append((time.monotonic(), cpu, int(fields[21]) * PAGE_KB / 1024))
        time.sleep(every)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", required=True, help="where the case study's data are (generated there if missing)")
    ap.add_argument("--tree", default=str(ROOT), help="the checkout whose tnnc runs (default: this one)")
    ap.add_argument("--every", type=float, default=0.25, help="sampling period, s")
    ap.add_argument("--min", type=float, default=0.4, help="the shortest stretch printed, s")
    a = ap.parse_args(argv)
    if not Path("/proc/self/stat").is_file():
        print("error: needs Linux's /proc", file=sys.stderr)
        return 1
    tree = Path(a.tree).resolve()
    if not (tree / "tnn_dsl" / "cli").is_dir() or not (tree / "networks" / "peltier_heatpipe" / "m1.thn").is_file():
        print(f"error: {tree} is not a tnn_dsl checkout (no tnn_dsl/cli or networks/peltier_heatpipe/m1.thn)",
              file=sys.stderr)
        return 1
    from tnn_dsl.studies.casestudy import generate_case_study

    data = Path(a.dir) / "cs"
    if not (data / "train.csv").is_file():
        generate_case_study(data, widen=(), n_ood=0)
    cmd = [sys.executable, "-c", "import sys; from tnn_dsl.cli import main; sys.exit(main())", "diagnose",
           str(tree / "networks" / "peltier_heatpipe" / "m1.thn"), str(data / "train.csv"), "--val",
           str(data / "val.csv"), "--json", str(Path(a.dir) / "diagnosis.json")]
    env = dict(os.environ, PYTHONPATH=str(tree))
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    samples: list[tuple[float, float, float]] = []
    done = threading.Event()
    sampler = threading.Thread(target=_sample, args=(proc.pid, a.every, samples, done), daemon=True)
    sampler.start()
    lines: list[tuple[float, str]] = []
    assert proc.stdout is not None
    for line in proc.stdout:
        lines.append((time.monotonic(), line.rstrip("\n")))
    rc = proc.wait()
    t_end = time.monotonic()
    done.set()
    sampler.join()
    if rc != 0:
        print("\n".join(text for _, text in lines[-20:]), file=sys.stderr)
        print(f"error: tnnc diagnose exited with {rc}", file=sys.stderr)
        return 1
    marks = [(t, text) for t, text in lines if re.match(r"\[ *[0-9.]+ s\]", text)] + [(t_end, "end")]
    print(f"{'start':>6} {'length':>7} {'cores':>6} {'RSS MB':>7}  stretch opened by")
    for (ta, text), (tb, _) in zip(marks, marks[1:]):
        if tb - ta < a.min:
            continue
        inside = [s for s in samples if ta <= s[0] <= tb]
        if len(inside) >= 2:
            cores = (inside[-1][1] - inside[0][1]) / max(inside[-1][0] - inside[0][0], 1e-9)
            rss = max(s[2] for s in inside)
            print(f"{ta - t0:6.1f} {tb - ta:6.1f}s {100 * cores:5.0f}% {rss:7.0f}  {text[:100]}")
    busy = samples[-1][1] / max(samples[-1][0] - t0, 1e-9) if samples else float("nan")
    print(f"wall {t_end - t0:.1f} s; {100 * busy:.0f} % of one core on average; peak resident "
          f"{max((s[2] for s in samples), default=float('nan')):.0f} MB (sampled every {a.every} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
