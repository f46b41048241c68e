"""Where the diagnosis' time goes (issue 18): ``tnn_dsl.diagnose`` of the case study from M1 (as
``bench_diagnose.py``: 4 h of training, 2 h held out; no MLP check) with the engine's calls wrapped to count them and
sum their wall time, and JAX's compilation events summed. One candidate fit at a time unless ``--threads`` says
otherwise (with more, the sums overlap).

    python benchmarks/profile_diagnose.py --dir /tmp/cs_profile                       # as shipped
    python benchmarks/profile_diagnose.py --dir /tmp/cs_profile --jacobian forward    # exact Jacobians steering
    python benchmarks/profile_diagnose.py --dir /tmp/cs_profile --backend torch --rounds 1 --budget 300

Prints the doctor's progress lines with their time, then one line per wrapped call (count, seconds, ms per call),
the compilation sums and the session's own timings; nothing is written but the generated data under ``--dir``.
The call times include the compilations their first calls trigger.
"""

from __future__ import annotations

import argparse
import collections
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

M1 = ROOT / "networks" / "peltier_heatpipe" / "m1.thn"
CALLS = ("fit", "jacobian", "_train_sse", "simulate", "forced_jacobian", "point_derivs")


def _wrap(owner, name: str, label: str, times: dict, counts: collections.Counter) -> None:
    f = getattr(owner, name)

    def timed(*a, **k):
        t = time.perf_counter()
        try:
            return f(*a, **k)
        finally:
            times[label] += time.perf_counter() - t
            counts[label] += 1

    setattr(owner, name, timed)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", default=None, help="where the case study's data are (generated there if missing)")
    ap.add_argument("--rounds", type=int, default=4, help="the doctor's max_rounds")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--jacobian", choices=("difference", "forward"), default=None,
                    help="how the Levenberg–Marquardt steps take their Jacobians (default: the doctor's LM_JACOBIAN)")
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--budget", type=float, default=None, help="the doctor's budget_s (default: none)")
    a = ap.parse_args(argv)

    from jax import monitoring

    import tnn_dsl.doctor.engine as E
    from tnn_dsl.doctor import diagnose
    from tnn_dsl.studies.casestudy import generate_case_study

    work = Path(a.dir) if a.dir else Path(tempfile.mkdtemp(prefix="profile_diagnose_"))
    data = work / "cs"
    if not (data / "train.csv").is_file():
        generate_case_study(data, widen=(), n_ood=0)
    if a.jacobian:
        E.LM_JACOBIAN = a.jacobian
    times: dict[str, float] = collections.defaultdict(float)
    counts: collections.Counter = collections.Counter()
    for name in CALLS:
        _wrap(E._Engine, name, name, times, counts)
    compiled: dict[str, float] = collections.defaultdict(float)
    n_compiled: collections.Counter = collections.Counter()

    def on_event(event: str, seconds: float, **_kw) -> None:
        if "/compile/" in event:
            compiled[event] += seconds
            n_compiled[event] += 1

    monitoring.register_event_duration_secs_listener(on_event)
    t0 = time.perf_counter()
    d = diagnose(str(M1), [str(data / "train.csv")], val=[str(data / "val.csv")], threads=a.threads,
                 max_rounds=a.rounds, mlp_check=False, backend=a.backend, budget_s=a.budget,
                 progress=lambda s: print(f"[{time.perf_counter() - t0:6.1f}] {s}", flush=True))
    print(f"total {time.perf_counter() - t0:.1f} s; gain ÷{d.baseline['val_mae'] / d.extended['val_mae']:.2f}; "
          f"accepted: {'; '.join(f.words[:70] for f in d.accepted) or 'nothing'}")
    for name in CALLS:
        if counts[name]:
            print(f"{name:16s} {counts[name]:6d} calls {times[name]:8.1f} s {1e3 * times[name] / counts[name]:8.1f} ms")
    for event in sorted(compiled):
        print(f"{event:50s} {n_compiled[event]:6d} {compiled[event]:8.1f} s")
    print("timings:", d.timings)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
