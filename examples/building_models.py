"""Bacher & Madsen's building models, fitted to their real data and judged on the part not fitted.

Networks: ``networks/building/{ti,tite,tith,titeth}.thn`` — Bacher & Madsen (2011), "Identifying suitable
models for the heat dynamics of buildings", Energy and Buildings 43: the interior (Ti), with the building
envelope (Te), with the heaters' own heat capacity (Th), and both.

Data (third-party, real measurements; see ``../shared/data/README.md``): ``bacher_madsen_inputPRBS1.csv``,
DTU's CTSM-R building example (the Bacher & Madsen case study; copy from Nilavro/BSSPy ``data/inputPRBS1.csv``
@ 238449b6, no licence stated there): 1691 × 5 min (140.8 h) of outdoor temperature ``Ta``, solar irradiance
``Ps``, PRBS electric heating ``Ph`` and indoor temperature ``yTi``. **Training: the first 70 % (1184 rows);
judged on the last 30 %** (507 rows, about 42 h), which nothing is fitted on.

Each model is fitted by ``tnn_dsl.train`` with default options (output error; a training file this short is
fitted as one free run from a fitted initial state, i.e. single shooting) and judged on the held-out part:

* **free run, held out as its own file** (the simulation question, for a file the model has never seen):
  ``tm.evaluate(tail)``; the initial state is estimated on a burn-in at the start of the tail (the default
  ``init="estimate"``, a tenth of the file), which is not scored;
* **free run, continued**: one simulation over the whole file (its start estimated from the whole file's
  burn-in), scored on the held-out rows — what ``tnnc simulate M --data whole.csv`` shows;
* **trainer's validation**: the same model trained again with the tail as validation data
  (``tnn_dsl.train(net, [head], [tail])``; early stopping on it) — its ``meta["metrics"]["validation"]`` is
  ``evaluate`` of the tail of that model;
* the held-out file again with each initial-state rule (``estimate``, ``filter``, ``measured``, ``steady``):
  what the start of a free run does to the score;
* **one-step-ahead** (Bacher & Madsen's question): an extended Kalman filter (``tnn_dsl.estimation.kalman.ekf``)
  with one process-noise level tuned on the training part by likelihood (``tune_process_noise``), run over the
  whole file; the RMS of its innovations (one-step prediction errors) on the held-out part.

Bacher & Madsen select Ti → TiTh → TiTeTh by likelihood-ratio tests on parameters fitted by maximum
likelihood of the one-step predictor; the tables above use output-error fits. The second part
(``--part objectives``) fits every model to the **whole file** under both objectives (``tnn_dsl.train(...,
objective="output-error" | "ml")``): log-likelihood, AIC, BIC, the free-run MAE, every estimate with its standard
error (CTSM-R's table), and the likelihood-ratio steps Ti → TiTh → TiTeTh and Ti → TiTe → TiTeTh.

    python examples/building_models.py                       # both parts, JAX, a few minutes
    python examples/building_models.py --part objectives     # the whole file under both objectives
    python examples/building_models.py --backend torch
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tnn_dsl  # noqa: E402
from tnn_dsl.data import read_data  # noqa: E402
from tnn_dsl.data.experiment import split_by_time  # noqa: E402
from tnn_dsl.estimation.kalman import ekf, tune_process_noise  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "bacher_madsen_inputPRBS1.csv"
MODELS = ["ti", "tite", "tith", "titeth"]
RULES = ("estimate", "filter", "measured", "steady")
"""The initial-state rules (``tnn_dsl.fit.initial``) compared on the held-out file."""
LABEL = {"ti": "Ti", "tite": "TiTe", "tith": "TiTh", "titeth": "TiTeTh"}


def continued_mae(tm, whole, split: int, backend: str) -> float:
    """MAE (K) of one free run over the whole file, scored on the rows from ``split`` on."""
    (p,) = tm.predict(whole, backend=backend)
    err = np.asarray(p["y"])[split:] - np.asarray(p["measured"])[split:]
    return float(np.mean(np.abs(err[np.isfinite(err)])))


PATHS = [("ti", "tith"), ("tith", "titeth"), ("ti", "tite"), ("tite", "titeth")]
"""The likelihood-ratio steps printed: Bacher & Madsen's forward selection (Ti → TiTh → TiTeTh) and the envelope
route (Ti → TiTe → TiTeTh)."""


def objectives(be: str) -> int:
    """Every model fitted to the whole file under both objectives: log-likelihoods, AIC/BIC, the estimates with
    their standard errors, and the likelihood-ratio steps between nested models."""
    from scipy.stats import chi2

    from tnn_dsl.estimation import estimation_summary

    fits = {}
    for name in MODELS:
        net = tnn_dsl.load(ROOT / "networks" / "building" / f"{name}.thn")
        (whole,) = read_data(net, DATA, time_unit="h")
        for obj in ("output-error", "ml"):
            t0 = time.perf_counter()
            tm = tnn_dsl.train(net, [whole], backend=be, objective=obj)
            fits[name, obj] = (tm.meta["estimation"], time.perf_counter() - t0, tm.evaluate(whole, backend=be)["mae"])
            print(f"{name} {obj}: done in {fits[name, obj][1]:.0f} s", file=sys.stderr, flush=True)
    print(f"\nBacher & Madsen building models on the whole of {DATA.name} (1691 rows), both objectives ({be})\n")
    print("| model | objective | k | log L | AIC | BIC | free-run MAE (K) | estimates without a std. error | "
          "time (s) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for (name, obj), (e, sec, mae) in fits.items():
        nose = ", ".join(r["name"] for r in e["rows"] if r["status"] != "ok") or "—"
        print(f"| {LABEL[name]} | {obj} | {e['n_params']} | {e['loglik']:.2f} | {e['aic']:.2f} | {e['bic']:.2f} | "
              f"{mae:.3f} | {nose} | {sec:.0f} |")
    print("\nLikelihood-ratio steps (`--objective ml`; LR = 2 (log L_B − log L_A), χ² with k_B − k_A degrees of "
          "freedom):\n")
    print("| step | log L_A | log L_B | LR | df | p | AIC_B − AIC_A | BIC_B − BIC_A |")
    print("|---|---|---|---|---|---|---|---|")
    for a, b in PATHS:
        ea, eb = fits[a, "ml"][0], fits[b, "ml"][0]
        lr, df = 2.0 * (eb["loglik"] - ea["loglik"]), eb["n_params"] - ea["n_params"]
        p = float(chi2.sf(max(lr, 0.0), df))
        p_text = "< 1e-300" if p < 1e-300 else f"{p:.3g}"  # underflow: a p-value printed as 0 is not one
        print(f"| {LABEL[a]} → {LABEL[b]} | {ea['loglik']:.2f} | {eb['loglik']:.2f} | {lr:.1f} | {df} | "
              f"{p_text} | {eb['aic'] - ea['aic']:.1f} | {eb['bic'] - ea['bic']:.1f} |")
    for name in MODELS:
        for obj in ("ml", "output-error"):
            print("\n```\n" + estimation_summary(fits[name, obj][0]) + "\n```")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--part", choices=("held-out", "objectives", "all"), default="all",
                    help="held-out: the 70/30 free-run comparison; objectives: the whole file under both "
                         "objectives with standard errors and the likelihood-ratio steps")
    args = ap.parse_args(argv)
    if not DATA.exists():
        print(f"data file not found: {DATA}", file=sys.stderr)
        return 1
    be = args.backend
    if args.part == "objectives":
        return objectives(be)
    rows = []
    burn = None
    for name in MODELS:
        t0 = time.perf_counter()
        net = tnn_dsl.load(ROOT / "networks" / "building" / f"{name}.thn")
        (whole,) = read_data(net, DATA, time_unit="h")
        head, tail = split_by_time(whole, 0.7)
        tm = tnn_dsl.train(net, [head], backend=be, seed=args.seed)
        free_train = tm.evaluate(head, backend=be)["mae"]
        (p,) = tm.predict(tail, backend=be)
        burn = p["burn_in"]
        held_out = tm.evaluate(tail, backend=be)["mae"]
        by_rule = {r: tm.evaluate(tail, backend=be, init=r)["mae"] for r in RULES}
        cont = continued_mae(tm, whole, head.n_steps, be)
        tv = tnn_dsl.train(net, [head], [tail], backend=be, seed=args.seed)
        val = tv.meta["metrics"]["validation"]["mae"]
        assert abs(val - tv.evaluate(tail, backend=be)["mae"]) <= 1e-9 * max(val, 1e-12)
        model, params = tm.compiled(be), tm.backend_params(be)
        q, _ = tune_process_noise(model, params, head.inputs, head.outputs, head.dt, ["Ti"])
        # the filter runs over the whole file (it needs the state at the split); scored on the held-out rows
        res = ekf(model, params, whole.inputs, whole.outputs, whole.dt, ["Ti"], process_noise=q)
        innov = res.innovations[head.n_steps:, 0]
        innov = innov[np.isfinite(innov)]
        rms = float(np.sqrt(np.mean(innov ** 2)))
        k = sum(1 for p_ in net.params if p_.free)
        rows.append((LABEL[name], len(net.nodes), k, free_train, held_out, cont, val, q, rms, time.perf_counter() - t0,
                     by_rule))
        print(f"{name}: done in {rows[-1][-2]:.0f} s", file=sys.stderr, flush=True)
    b = burn
    print(f"\nBacher & Madsen building models on {DATA.name}: fitted on the first 70 % (1184 rows), judged on the "
          f"last 30 % (507 rows) ({be}, seed {args.seed})")
    print(f"Held out as its own file: initial state estimated on a burn-in of {b} samples ({b * 5 / 60:g} h) at the "
          f"start of the tail, not scored.\n")
    print("| model | states | free parameters | free-run MAE train (K) | held out, own file (K) | "
          "continued free run, held-out rows (K) | trainer's validation (K) | process noise q (K/√s) | "
          "one-step RMS held out (K) | time (s) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, ns, k, ft, ho, cont, val, q, rms, sec, _ in rows:
        print(f"| {name} | {ns} | {k} | {ft:.3f} | {ho:.3f} | {cont:.3f} | {val:.3f} | {q:g} | {rms:.4f} | {sec:.0f} |")
    print("\nHeld out as its own file, by initial-state rule (the same models; `tm.evaluate(tail, init=rule)`):\n")
    print("| model | " + " | ".join(f"{r} (K)" for r in RULES) + " |")
    print("|---|" + "---|" * len(RULES))
    for row in rows:
        print(f"| {row[0]} | " + " | ".join(f"{row[-1][r]:.3f}" for r in RULES) + " |")
    return objectives(be) if args.part == "all" else 0


if __name__ == "__main__":
    raise SystemExit(main())
