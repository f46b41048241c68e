"""Where a trained model's evaluation of many files spends its time, and how its burn-in fits go (issue 18): the
initial state of each file is a Gauss–Newton fit on the file's burn-in (``tnn_dsl.fit.initial``), then the free run.

    python benchmarks/bench_free_runs.py --models m4 --files 10 --modes jax     # trains and saves the model first
    python benchmarks/profile_burn_in_fits.py --model m4 --files 10 --backend jax
    python benchmarks/profile_burn_in_fits.py --model m4 --files 10 --backend torch

Reads the model and the +40 % out-of-distribution files ``bench_free_runs.py`` left in ``--cache``, evaluates the
files in one call (after a first call that compiles) and prints, per file, the Gauss–Newton steps, the calls for the
burn-in's readings and for its Jacobian, the weighted cost at the start and at the end and the file's MAE; the
weighted cost at every step of the first file; and the time of the whole call against the time spent finding the
initial states. Nothing is written."""

from __future__ import annotations

import argparse
import glob
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv=None) -> int:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", default="m4")
    ap.add_argument("--files", type=int, default=10)
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "tnn_bench_free_runs"),
                    help="where the model (models/MODEL) and the +40 %% files (data/ood_40_*.csv) are: "
                         "bench_free_runs.py's cache, or a `tnnc demo --out DIR`")
    ap.add_argument("--every-file", action="store_true",
                    help="print every file's weighted cost at each Gauss–Newton step, not only the first file's")
    a = ap.parse_args(argv)

    import tnn_dsl.fit.initial as initial
    import tnn_dsl.fit.simulation as simulation
    from tnn_dsl.data import read_data
    from tnn_dsl.fit.model_files import load_model

    mdir = Path(a.cache) / "models" / a.model
    files = sorted(glob.glob(str(Path(a.cache) / "data" / "ood_40_*.csv")))[:a.files]
    if not mdir.is_dir() or not files:
        print(f"no model or files under {a.cache}: run `python benchmarks/bench_free_runs.py --models {a.model} "
              f"--files {a.files} --modes jax` first", file=sys.stderr)
        return 2
    tm = load_model(str(mdir))
    if a.backend == "torch":
        tm.compiled("torch").compile_torch_rollouts()
    exps = [e for f in files for e in read_data(tm.network, f)]
    tm.evaluate(exps, backend=a.backend)  # compiles

    fits: list[dict] = []
    real_init, real_step, real_state = initial._BurnInFit.__init__, initial.gauss_newton_step, simulation.initial_state

    def counted(fn, key):
        if fn is None:
            return None

        def f(*args):
            fits[-1][key] += 1
            return fn(*args)

        return f

    def init(self, *args, **kw):
        real_init(self, *args, **kw)
        self.fy, self.fJ, self.fyJ = counted(self.fy, "readings"), counted(self.fJ, "jacobian"), counted(self.fyJ,
                                                                                                         "both")

    def step(J, r, W, P, d):
        fits[-1]["costs"].append(float(np.sum((W * r) ** 2) + np.sum((P * d) ** 2)))
        return real_step(J, r, W, P, d)

    spent = [0.0]

    def state(*args, **kw):
        fits.append({"readings": 0, "jacobian": 0, "both": 0, "costs": []})
        t = time.perf_counter()
        try:
            return real_state(*args, **kw)
        finally:
            spent[0] += time.perf_counter() - t

    initial._BurnInFit.__init__, initial.gauss_newton_step, simulation.initial_state = init, step, state
    try:
        t = time.perf_counter()
        ev = tm.evaluate(exps, backend=a.backend)
        total = time.perf_counter() - t
    finally:
        initial._BurnInFit.__init__, initial.gauss_newton_step, simulation.initial_state = (real_init, real_step,
                                                                                            real_state)
    print(f"{a.model} on {a.backend}, {len(exps)} files of {exps[0].n_steps} samples (+40 %), one call")
    print("| file | Gauss–Newton steps | readings calls | Jacobian calls | readings + Jacobian calls | cost first | "
          "cost last step | MAE (mK) |")
    print("|---|---|---|---|---|---|---|---|")
    for f, fit, e in zip(files, fits, ev["experiments"]):
        c = fit["costs"] or [float("nan")]
        print(f"| {Path(f).name} | {len(fit['costs'])} | {fit['readings']} | {fit['jacobian']} | {fit['both']} | "
              f"{c[0]:.4g} | {c[-1]:.4g} | {e['mae'] * 1e3:.2f} |")
    if a.every_file:
        for f, fit in zip(files, fits):
            print(f"weighted cost at each step of {Path(f).name}: " + ", ".join(f"{c:.8g}" for c in fit["costs"]))
    print("weighted cost at each step of the first file: " + ", ".join(f"{c:.4g}" for c in fits[0]["costs"]))
    print(f"mean MAE {np.mean([e['mae'] for e in ev['experiments']]) * 1e3:.2f} mK; the call {total:.2f} s, of it "
          f"{spent[0]:.2f} s finding the initial states")
    return 0


if __name__ == "__main__":
    sys.exit(main())
