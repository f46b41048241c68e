"""The thesis's case study (chapter 5): M1–M5 in and out of distribution, with the thesis's ratios beside ours.

    .venv/bin/python examples/thesis_case_study.py [--out study] [--time-limit 240] [--epochs 300] [--backend jax]

Generates (or reuses) the case-study data in OUT/data, trains M1–M5 (Table 5.1; M5 reuses M4's frozen
Peltier network), evaluates the validation MAE and max error and the out-of-distribution MAE over input
bounds widened by 10–40 % with 10 data sets per level (Figure 5.6), writes OUT/results.json,
OUT/results.md, OUT/ood.png and OUT/validation.png, and prints the tables. The logic is
``tnn_dsl.studies.thesis`` (``tnnc demo`` runs the same with smaller budgets).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tnn_dsl.studies.thesis import StudyConfig, plot_study, ratios_table, results_table, run_study  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="study")
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--epochs", type=int, default=300)
    ap.add_argument("--time-limit", type=float, default=240.0, help="seconds of Adam per model")
    ap.add_argument("--lbfgs", type=int, default=100, help="L-BFGS polish iterations per model")
    ap.add_argument("--n-ood", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    cfg = StudyConfig(backend=args.backend, epochs=args.epochs, time_limit=args.time_limit, lbfgs_iters=args.lbfgs,
                      n_ood=args.n_ood, seed=args.seed)
    runs: dict = {}
    res = run_study(args.out, config=cfg, progress=lambda m: print(f"[{time.monotonic() - t0:5.0f} s] {m}", flush=True),
                    validation_runs=runs)
    res["models_dir"] = str(Path(args.out) / "models")
    plots = plot_study(res, args.out, validation_runs=runs)
    text = "\n\n".join([
        f"Command: `python examples/thesis_case_study.py --out {args.out} --epochs {args.epochs} "
        f"--time-limit {args.time_limit:g} --lbfgs {args.lbfgs} --n-ood {args.n_ood} --backend {args.backend}` "
        f"({time.monotonic() - t0:.0f} s)",
        results_table(res), ratios_table(res)] + [f"![{Path(p).stem}]({Path(p).name})" for p in plots])
    (Path(args.out) / "results.md").write_text(text + "\n", encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
