"""Cost per integration step against network size, on both backends (issue 18: large networks in linear time).

Networks: square plate meshes from ``tnn_dsl.studies.large_networks.plate_thn`` (aluminium cells of 20 mm,
10 mm thick, so every size has the same time constants and RK4 at 1 s needs no sub-steps; about 3 links per
node: two to neighbours and one to ambient; two heaters and three sensors). Each (backend, size, form) runs
in its own process so that its peak memory is its own:

* parse and compile times; the first rollout (tracing and compilation) separately;
* forward rollout cost per integration step (RK4, float64, a single sequence), the median of 3 timed runs
  of a length chosen to take about a second;
* the steady state (Newton; Newton–Krylov for sparse models) for the same inputs;
* peak resident memory of the process.

The sparse form (gather/scatter, the default from 64 states) is measured at every size; the dense form
(one product per matrix, the default below 64 states) up to ``--dense-max`` nodes, to show what it costs.
The log-log slope of cost against nodes is a least-squares fit over the sizes; "within 2×" compares the
cost per node-step at the largest sizes with its smallest value over the sizes of at least 1000 nodes.
Finally a 10 000-node plate simulated for 1000 steps, timed end to end (compile included and not).

    python benchmarks/bench_scaling.py                  # sizes 10 … 20 000, writes BENCHMARKS.md
    python benchmarks/bench_scaling.py --quick          # 10 … 3000, no 10 000-node run
    python benchmarks/bench_scaling.py --sizes 10,300 --no-write --json out.json   # no end-to-end run
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))

SIZES = (10, 30, 100, 300, 1000, 3000, 10000, 20000)
QUICK_SIZES = (10, 30, 100, 300, 1000, 3000)


def _worker(backend: str, n: int, form: str, steps_total: int | None) -> dict:
    import numpy as np

    import tnn_dsl
    from tnn_dsl.studies.large_networks import plate_size, plate_thn

    out: dict = {"backend": backend, "n_target": n, "form": form}
    t0 = time.perf_counter()
    text = plate_thn(*plate_size(n))
    net = tnn_dsl.loads(text, "plate.thn")
    t1 = time.perf_counter()
    model = tnn_dsl.compile(net, backend, sparse=(form == "sparse"))
    t2 = time.perf_counter()
    out.update(nodes=len(net.nodes), links=len(net.links), parse_s=t1 - t0, compile_s=t2 - t1)
    params = model.init_params()
    ni = len(model.input_names)
    T0 = np.full(len(model.state_names), 293.15)

    def inputs(N):
        U = np.zeros((N, ni))
        U[:, 0] = 293.15
        U[:, 1:] = 20.0
        return U

    def run(N):
        s, y = model.rollout(params, T0, inputs(N), 1.0, "rk4", substeps=1)
        return float(np.asarray(model.xp.to_numpy(y))[-1, 0])

    if steps_total:  # the end-to-end run: first call (compile) and a second call of the same length
        a = time.perf_counter()
        run(steps_total + 1)
        b = time.perf_counter()
        run(steps_total + 1)
        c = time.perf_counter()
        out.update(steps=steps_total, first_call_s=b - a, second_call_s=c - b, end_to_end_s=b - t0)
    else:
        a = time.perf_counter()
        run(11)
        out["first_call_s"] = time.perf_counter() - a
        # a length that takes about a second (at least 20 steps, at most 20 000)
        run(101)  # JAX compiles per length: time the second call
        a = time.perf_counter()
        run(101)
        per = max((time.perf_counter() - a) / 100, 1e-7)
        N = int(min(20000, max(20, 1.0 / per)))
        run(N + 1)  # JAX: compile this length once
        times = []
        for _ in range(3):
            a = time.perf_counter()
            run(N + 1)
            times.append((time.perf_counter() - a) / N)
        times.sort()
        out.update(steps=N, us_per_step=1e6 * times[1])
        u0 = inputs(1)[0]
        a = time.perf_counter()
        T = model.steady_state(params, u0)
        np.asarray(model.xp.to_numpy(T))
        out["steady_first_s"] = time.perf_counter() - a
        a = time.perf_counter()
        T = model.steady_state(params, u0)
        Tn = np.asarray(model.xp.to_numpy(T))
        out["steady_s"] = time.perf_counter() - a
        out["steady_residual"] = float(np.max(np.abs(model.xp.to_numpy(model.rhs(params, Tn, u0)))))
    out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def _spawn(backend, n, form, steps_total=None, timeout=1800) -> dict:
    cmd = [sys.executable, __file__, "--worker", json.dumps([backend, n, form, steps_total])]
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"backend": backend, "n_target": n, "form": form, "error": f"over {timeout} s"}
    for line in reversed(r.stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    return {"backend": backend, "n_target": n, "form": form, "error": (r.stderr or r.stdout)[-400:]}


def _slope(rows):
    xs = [math.log(r["nodes"]) for r in rows]
    ys = [math.log(r["us_per_step"]) for r in rows]
    if len(xs) < 2:
        return float("nan")
    mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
    return sum((x - mx) * (y - my) for x, y in zip(xs, ys)) / sum((x - mx) ** 2 for x in xs)


def _fmt(v, digits=3):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:.{digits}g}"


def render(results: list[dict], e2e: list[dict], note: str) -> str:
    lines = [note, "", "| backend | form | nodes | links | µs/step | µs per node-step | first call s | steady state s "
             "| steady residual K/s | parse s | compile s | peak RSS MB |", "|" + "---|" * 12]
    for r in results:
        if "error" in r:
            lines.append(f"| {r['backend']} | {r['form']} | ~{r['n_target']} | | failed: {r['error'][:80]} "
                         "| | | | | | | |")
            continue
        lines.append(f"| {r['backend']} | {r['form']} | {r['nodes']} | {r['links']} | {_fmt(r['us_per_step'])} | "
                     f"{_fmt(r['us_per_step'] / r['nodes'])} | {_fmt(r['first_call_s'])} | {_fmt(r['steady_s'])} | "
                     f"{_fmt(r['steady_residual'], 2)} | {_fmt(r['parse_s'])} | {_fmt(r['compile_s'])} | "
                     f"{r['peak_rss_mb']:.0f} |")
    lines += ["", "| backend | form | sizes | log-log slope (all sizes) | slope (≥ 1000 nodes) | "
                  "max/min µs per node-step (≥ 1000 nodes) |", "|---|---|---|---|---|---|"]
    for be in ("jax", "torch"):
        for form in ("sparse", "dense"):
            rows = [r for r in results if r["backend"] == be and r["form"] == form and "error" not in r]
            if len(rows) < 2:
                continue
            big = [r for r in rows if r["nodes"] >= 1000]
            per = [r["us_per_step"] / r["nodes"] for r in big]
            ratio = max(per) / min(per) if len(per) >= 2 else float("nan")
            lines.append(f"| {be} | {form} | {rows[0]['nodes']}–{rows[-1]['nodes']} | {_slope(rows):.2f} | "
                         f"{_slope(big):.2f} | {_fmt(ratio)} |")
    if e2e:
        lines += ["", "10 000-node plate, 1000 RK4 steps of 1 s, one process each (end to end = generate, parse, "
                      "compile, first rollout):", "",
                  "| backend | nodes | end to end s | first rollout s | second rollout s | peak RSS MB |",
                  "|---|---|---|---|---|---|"]
        for r in e2e:
            if "error" in r:
                lines.append(f"| {r['backend']} | ~{r['n_target']} | failed: {r['error'][:80]} | | | |")
                continue
            lines.append(f"| {r['backend']} | {r['nodes']} | {_fmt(r['end_to_end_s'])} | {_fmt(r['first_call_s'])} | "
                         f"{_fmt(r['second_call_s'])} | {r['peak_rss_mb']:.0f} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="sizes up to 3000, no 10 000-node run")
    ap.add_argument("--sizes", default=None, help="comma-separated node counts (default 10 … 20 000)")
    ap.add_argument("--backends", default="jax,torch")
    ap.add_argument("--dense-max", type=int, default=3000, help="largest size measured in the dense form")
    ap.add_argument("--json", default=None, metavar="FILE", help="also write the raw results here")
    ap.add_argument("--no-write", action="store_true", help="do not write BENCHMARKS.md")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        backend, n, form, steps_total = json.loads(args.worker)
        print(json.dumps(_worker(backend, n, form, steps_total)))
        return 0
    sizes = [int(s) for s in args.sizes.split(",")] if args.sizes else list(QUICK_SIZES if args.quick else SIZES)
    backends = args.backends.split(",")
    t_start = time.time()
    results = []
    for be in backends:
        for n in sizes:
            forms = ["sparse"] + (["dense"] if n <= args.dense_max else [])
            for form in forms:
                r = _spawn(be, n, form)
                results.append(r)
                print(json.dumps(r), flush=True)
    e2e = []
    if not args.quick and not args.sizes:  # the 10 000-node end-to-end run belongs to the full run
        for be in backends:
            r = _spawn(be, 10000, "sparse", steps_total=1000)
            e2e.append(r)
            print(json.dumps(r), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps({"sizes": results, "end_to_end": e2e}, indent=1))
    note = (f"Plate meshes (`tnn_dsl.studies.large_networks.plate_thn`), RK4 at 1 s without sub-steps, float64, "
            f"a single sequence; one process per row; wall time {time.time() - t_start:.0f} s. The machine is "
            "shared (2 cores): the ratios and slopes come from this one run.")
    text = render(results, e2e, note)
    print(text)
    if not args.no_write:
        from _report import write_section

        write_section("scaling", text, title="Network size: cost per step from 10 to 20 000 nodes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
