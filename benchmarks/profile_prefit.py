"""The pre-fit of M4's `replace`-mode Peltier MLP (`tnn_dsl/fit/prefit.py`): time, fit and the backends' agreement.

For each backend, the trainer's own set-up on the demo's data (4 h training, `tnnc demo`'s case study, generated once
into a cache directory): initial parameters, the nominal run, the normalisation, then `_Trainer.prefit_replace`. It
prints the pre-fit's time, its relative RMS error against the nominal law on every sample of the run, the largest
weight, and at the end the largest difference between the backends' weights. ``--ridge`` and ``--evaluations``
vary the weight decay and the Levenberg–Marquardt budget; ``--lbfgs`` runs ``fit_weights``' L-BFGS-B path (for
functions of more than ``PREFIT_LM_MAX_WEIGHTS`` weights). The pre-fit before 2026-12-02 (L-BFGS-B on 4000 samples,
no weight decay): this file copied into a worktree of commit 556c60a and run there.

``--first-epochs``: M4 trained for 8 epochs (no polish) on the 40-minute case study of ``tests/test_train.py``, with
each ``--ridge``: the validation MAE at the start and after each epoch (how far Adam's first steps throw the fit).

    python benchmarks/profile_prefit.py
    python benchmarks/profile_prefit.py --backends jax --evaluations 20 40 60 100
    python benchmarks/profile_prefit.py --ridge 0 1e-8 1e-7 1e-6 --backends jax
    python benchmarks/profile_prefit.py --first-epochs --ridge 0 1e-7
"""

from __future__ import annotations

import argparse
import functools
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
M4 = ROOT / "networks" / "peltier_heatpipe" / "m4.thn"


def _patched(ridge: float, evaluations: int, lbfgs: bool) -> None:
    """The trainer's ``fit_weights`` with this weight decay and budget (``lbfgs``: its L-BFGS-B path). On a tree
    before ``tnn_dsl/fit/prefit.py`` (this file copied into a worktree of 556c60a) nothing is patched: its own
    L-BFGS pre-fit runs."""
    try:
        from tnn_dsl.fit import prefit, trainer
    except ImportError:
        return

    prefit.PREFIT_MAX_EVALUATIONS = int(evaluations)
    prefit.PREFIT_LM_MAX_WEIGHTS = -1 if lbfgs else 2000
    trainer.fit_weights = functools.partial(prefit.fit_weights, ridge=float(ridge))


def _prefit_once(data: dict, backend: str) -> tuple[dict, float, dict]:
    """``(weights, seconds, relative RMS error per flow over the whole run)`` of the trainer's pre-fit of M4."""
    from tnn_dsl.compiler import compile as compile_network
    from tnn_dsl.data import as_experiments
    from tnn_dsl.fit.trainer import _Trainer
    from tnn_dsl.fit.training import make_config
    from tnn_dsl.lang import load

    net = load(str(M4))
    cfg = make_config(None, dict(backend=backend, seed=0))
    exps, vals = as_experiments(net, data["train"]), as_experiments(net, data["val"])
    model = compile_network(net, backend=backend, dtype=cfg.dtype, torch_compile=False)
    tr = _Trainer(net, exps, vals, cfg, model)
    params = tr.initial_params()
    nom, nom_bp, runs = tr.nominal_runs(params)
    tr.set_stats(params, nom, nom_bp, runs)
    t = time.perf_counter()
    tr.prefit_replace(params, nom, nom_bp, runs)
    seconds = time.perf_counter() - t
    T, U = np.concatenate(runs), np.concatenate([np.asarray(e.inputs, dtype=float) for e in exps])
    want = tr._nominal_flows(nom, nom_bp, T, U)
    got = model.heat_flows(model.from_numpy(params), tr.ops.asarray(T), tr.ops.asarray(U))
    err = {t: float(np.sqrt(np.mean((tr.ops.numpy(got[t]) - want[t]) ** 2) / np.mean(want[t] ** 2)))
           for t in ("pe.Q_hot", "pe.Q_cold")}
    weights = {k: np.asarray(v) for k, v in params.items()
               if k.startswith("fn_pe_Q_hot.") and k.split(".")[1][0] in "Wb"}
    return weights, seconds, err


def _first_epochs(ridge: float) -> list[float]:
    """Validation MAE (mK) at the start and after each of 8 epochs of M4 on the 40-minute case study."""
    import tnn_dsl
    from tnn_dsl.studies.casestudy import generate_case_study

    cs = generate_case_study(Path(tempfile.gettempdir()) / "tnn_profile_prefit_cs_short", n_ood=0, widen=(),
                             durations=(2400.0, 1200.0, 60.0))
    tm = tnn_dsl.train(M4, cs["train"], cs["val"], backend="jax", rollout="estimated", window=400.0, epochs=8,
                       lbfgs_iters=0, seed=0)
    return [1e3 * r["val_mae"] for r in tm.meta["curve"]]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backends", nargs="+", default=["jax", "torch"], choices=("jax", "torch"))
    ap.add_argument("--ridge", nargs="+", type=float, default=None, help="weight decays (default: PREFIT_RIDGE)")
    ap.add_argument("--evaluations", nargs="+", type=int, default=None,
                    help="Levenberg–Marquardt budgets (default: PREFIT_MAX_EVALUATIONS)")
    ap.add_argument("--lbfgs", action="store_true", help="the L-BFGS-B path on the same residuals, no weight decay")
    ap.add_argument("--first-epochs", action="store_true", help="M4's first 8 epochs on the 40-minute case study")
    ap.add_argument("--cache", default=str(Path(tempfile.gettempdir()) / "tnn_profile_prefit_cs"))
    args = ap.parse_args(argv)
    try:
        from tnn_dsl.fit import prefit

        ridge0, budget0 = prefit.PREFIT_RIDGE, prefit.PREFIT_MAX_EVALUATIONS
    except ImportError:  # the tree before the module: its L-BFGS pre-fit
        ridge0, budget0 = 0.0, 0
        args.lbfgs = True
    ridges = args.ridge if args.ridge is not None else [ridge0]
    budgets = args.evaluations or [budget0]
    if args.first_epochs:
        for ridge in ridges:
            _patched(ridge, budgets[0], args.lbfgs)
            curve = _first_epochs(ridge)
            print(f"ridge {ridge:g}: validation MAE (mK) start, epochs 1–8: " + ", ".join(f"{v:.0f}" for v in curve))
        return 0
    from tnn_dsl.studies.casestudy import generate_case_study

    data = generate_case_study(args.cache, n_ood=0, widen=())
    print("| method | ridge | evaluations | backend | seconds | relative RMS error (Q_hot, Q_cold) | largest weight |")
    print("|---|---|---|---|---|---|---|")
    for ridge in ridges:
        for budget in budgets:
            _patched(ridge, budget, args.lbfgs)
            fitted = {}
            for backend in args.backends:
                w, s, err = _prefit_once(data, backend)
                fitted[backend] = w
                print(f"| {'L-BFGS-B' if args.lbfgs else 'Levenberg–Marquardt'} | {ridge:g} | "
                      f"{'≤ 500 iterations' if args.lbfgs else budget} | {backend} | {s:.2f} | "
                      + ", ".join(f"{v:.2e}" for v in err.values())
                      + f" | {max(float(np.abs(v).max()) for v in w.values()):.3g} |")
            if len(fitted) == 2:
                a, b = fitted.values()
                print(f"|  |  |  | largest difference between the backends' weights | "
                      f"{max(float(np.abs(a[k] - b[k]).max()) for k in a):.2g} |  |  |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
