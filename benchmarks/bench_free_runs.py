"""Free runs of a trained model over many files (``TrainedModel.evaluate``, ``tnnc evaluate``): each file's initial
state estimated on its burn-in, then one free run over the file — per backend, and on torch eager against compiled.

    python benchmarks/bench_free_runs.py [--models m2,m4] [--files 6] [--epochs 200]

Each model of the case study (``networks/peltier_heatpipe/<name>.thn``) is trained on JAX as ``tnnc demo`` trains
it, saved, and evaluated on ``--files`` out-of-distribution files (2 h at 1 s each) in a fresh process per mode:
``jax``; ``torch-eager``; ``torch-compiled`` (an empty inductor cache: the compilation paid as on a new machine);
``torch-auto`` (the files in one call, the default rule ``tnn_dsl.fit.config.FREE_RUN_COMPILE_MIN_SAMPLES``).
Prints per mode the first call (compilation included), the median of the others, the whole evaluation and the
largest difference of a file's MAE from the first mode's (K); then the files in one call, twice (the first compiles
the batch's shape on JAX), where files alike in length run as one batched rollout
(``tnn_dsl.fit.simulation.free_runs``), and its largest MAE difference from the one-file calls. Nothing is written to
the repository; data and models go to ``--cache``."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MODES = ("jax", "torch-eager", "torch-compiled", "torch-auto")


def _worker(model_dir: str, files: list[str], mode: str) -> dict:
    """Evaluate the saved model on each file, one call per file; times in s and each file's MAE (K)."""
    from tnn_dsl.fit.model_files import load_model

    tm = load_model(model_dir)
    backend = "jax" if mode == "jax" else "torch"
    if mode == "torch-compiled":
        tm.compiled("torch").compile_torch_rollouts()
    times, maes = [], []
    if mode == "torch-auto":  # the files as one call, as `tnnc evaluate MODEL FILES...` makes it
        t = time.perf_counter()
        ev = tm.evaluate(files, backend=backend)
        times.append(time.perf_counter() - t)
        maes = [e["mae"] for e in ev["experiments"]]
    else:
        for f in files:
            t = time.perf_counter()
            ev = tm.evaluate([f], backend=backend)
            times.append(time.perf_counter() - t)
            maes += [e["mae"] for e in ev["experiments"]]
    one_call = None
    if len(files) > 1:  # then every file in one call, twice: alike files' runs go as one batch (free_runs)
        secs = []
        for _ in range(2):  # the first compiles the batch's shape on JAX
            t = time.perf_counter()
            ev = tm.evaluate(files, backend=backend)
            secs.append(time.perf_counter() - t)
        one_call = {"seconds": secs, "maes": [e["mae"] for e in ev["experiments"]]}
    return {"times": times, "maes": maes, "one_call": one_call,
            "compiled": bool(tm.compiled(backend).torch_compile) if backend == "torch" else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="m2,m4")
    ap.add_argument("--files", type=int, default=6)
    ap.add_argument("--epochs", type=int, default=200)
    ap.add_argument("--modes", default=",".join(MODES))
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "tnn_bench_free_runs"))
    ap.add_argument("--worker", nargs=3, metavar=("MODEL", "FILES_JSON", "MODE"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        model_dir, files, mode = args.worker
        print("RESULT " + json.dumps(_worker(model_dir, json.loads(files), mode)), flush=True)
        return 0

    import tnn_dsl
    from tnn_dsl.fit.training import train
    from tnn_dsl.studies.casestudy import generate_case_study

    cache = Path(args.cache)
    cs = generate_case_study(cache / "data", widen=(0.4,), n_ood=args.files)
    files = cs["ood"]["40"][:args.files]
    print(f"{len(files)} files of 2 h at 1 s (+40 % widened inputs), {os.cpu_count()} cores")
    for name in args.models.split(","):
        net = tnn_dsl.load(str(ROOT / "networks" / "peltier_heatpipe" / f"{name}.thn"))
        mdir = cache / "models" / name
        t = time.perf_counter()
        train(net, cs["train"], cs["val"], backend="jax", epochs=args.epochs, lbfgs_iters=40, time_limit=70.0,
              out=mdir, force=True, log=lambda s: None)
        print(f"{name}: trained on JAX in {time.perf_counter() - t:.0f} s (the demo's settings: ≤ {args.epochs} "
              "Adam epochs, 40 L-BFGS, 70 s)", flush=True)
        ref = None
        for mode in args.modes.split(","):
            env = dict(os.environ)
            env.pop("TNN_TORCH_COMPILE", None)
            with tempfile.TemporaryDirectory(prefix="tnn_bench_inductor_") as inductor_cache:
                env["TORCHINDUCTOR_CACHE_DIR"] = inductor_cache
                t = time.perf_counter()
                proc = subprocess.run([sys.executable, __file__, "--worker", str(mdir), json.dumps(files), mode],
                                      capture_output=True, text=True, env=env, cwd=ROOT)
                wall = time.perf_counter() - t
            line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")), None)
            if line is None:
                print(f"  {mode:15s} failed:\n{proc.stderr[-2000:]}")
                continue
            r = json.loads(line[7:])
            ref = r["maes"] if ref is None else ref
            dev = max(abs(a - b) for a, b in zip(r["maes"], ref))
            ts = r["times"]
            rest = (f"then {statistics.median(ts[1:]):6.2f} s a file (median)" if len(ts) > 1
                    else "all files in one call")
            print(f"  {mode:15s} first {ts[0]:6.2f} s, {rest}; evaluation {sum(ts):6.1f} s "
                  f"(process {wall:5.1f} s); compiled: {r['compiled']}; max |ΔMAE| vs {args.modes.split(',')[0]} "
                  f"{dev:.2g} K", flush=True)
            one = r.get("one_call")
            if one:
                d1 = max(abs(a - b) for a, b in zip(one["maes"], r["maes"]))
                first, again = one["seconds"]
                print(f"  {'':15s} then the {len(files)} files in one call: {first:6.2f} s, again {again:6.2f} s "
                      f"({again / len(files):.3f} s a file; max |ΔMAE| vs one call a file {d1:.2g} K)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
