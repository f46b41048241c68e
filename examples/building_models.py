"""Bacher & Madsen's building models, fitted to their real data and judged on the part not fitted.

Networks: ``networks/building/{ti,tite,tith,titeth}.thn`` — Bacher & Madsen (2011), "Identifying suitable
models for the heat dynamics of buildings", Energy and Buildings 43: the interior (Ti), with the building
envelope (Te), with the heaters' own heat capacity (Th), and both.

Data (third-party, real measurements; see ``../shared/data/README.md``): ``bacher_madsen_inputPRBS1.csv``,
DTU's CTSM-R building example (the Bacher & Madsen case study; copy from Nilavro/BSSPy ``data/inputPRBS1.csv``
@ 238449b6, no licence stated there): 1691 × 5 min (140.8 h) of outdoor temperature ``Ta``, solar irradiance
``Ps``, PRBS electric heating ``Ph`` and indoor temperature ``yTi``. **Training: the first 70 %; judged on
the last 30 %** (about 42 h), which nothing is fitted on.

Each model is fitted by ``tnn_dsl.train`` with default options (output error; multiple shooting in windows
of 50 samples) and judged two ways on the held-out part:

* **free run** (the simulation question): MAE of the simulation from the state at the split;
* **one-step-ahead** (Bacher & Madsen's question): an extended Kalman filter (``tnn_dsl.estimation.kalman.ekf``)
  with one process-noise level tuned on the training part by likelihood (``tune_process_noise``); the RMS
  of its innovations (one-step prediction errors) on the held-out part.

Bacher & Madsen select Ti → TiTh → TiTeTh by likelihood-ratio tests on parameters fitted by maximum
likelihood of the one-step predictor; here the parameters are output-error fits, so the table is a
comparison in their spirit, not a reproduction of their estimates.

    python examples/building_models.py                 # JAX, about a minute
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if not DATA.exists():
        print(f"data file not found: {DATA}", file=sys.stderr)
        return 1
    rows = []
    for name in MODELS:
        t0 = time.perf_counter()
        net = tnn_dsl.load(ROOT / "networks" / "building" / f"{name}.thn")
        (exp,) = read_data(net, DATA, time_unit="h")
        head, tail = split_by_time(exp, 0.7)
        tm = tnn_dsl.train(net, [head], [tail], backend=args.backend, seed=args.seed)
        free_train = tm.evaluate(head, backend=args.backend)["mae"]
        free_val = tm.meta["metrics"]["validation"]["mae"]
        model, params = tm.compiled(args.backend), tm.backend_params(args.backend)
        q, _ = tune_process_noise(model, params, head.inputs, head.outputs, head.dt, ["Ti"])
        # the filter runs over the whole file (it needs the state at the split); scored on the held-out rows
        res = ekf(model, params, exp.inputs, exp.outputs, exp.dt, ["Ti"], process_noise=q)
        n0 = head.n_steps
        innov = res.innovations[n0:, 0]
        innov = innov[np.isfinite(innov)]
        rms = float(np.sqrt(np.mean(innov ** 2)))
        k = sum(1 for p in net.params if p.free)
        rows.append((name, len(net.nodes), k, free_train, free_val, q, rms, time.perf_counter() - t0))
        print(f"{name}: done in {rows[-1][-1]:.0f} s", file=sys.stderr, flush=True)
    print(f"\nBacher & Madsen building models on {DATA.name}: fitted on the first 70 %, judged on the last 30 % "
          f"({args.backend})\n")
    print("| model | states | free parameters | free-run MAE train (K) | free-run MAE held out (K) | "
          "process noise q (K/√s) | one-step RMS held out (K) | time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for name, ns, k, ft, fv, q, rms, sec in rows:
        print(f"| {name} | {ns} | {k} | {ft:.3f} | {fv:.3f} | {q:g} | {rms:.4f} | {sec:.0f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
