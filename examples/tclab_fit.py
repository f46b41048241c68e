"""Fit the TCLab two-heater network to real data and check it on data it has never seen.

Networks: ``networks/tclab/tclab.thn`` (two heater nodes, convection to ambient, conduction between the heaters,
heater gains in W/%; every C, G, gain and the ambient ``Ta`` are ``free``) and ``networks/tclab/tclab_ambient.thn``
(the same with ``Ta`` declared ``free … per experiment``: the ambient was not logged and differs between runs).

Data (third-party, real hardware; see ``../shared/data/README.md`` for the full attribution):

* ``tclab_kuntz_rawlings_prbs_openloop.csv``: from rawlings-group/mlid_2024 (``data/tclab_prbs.pickle``
  @ 9f1c939c), MIT licence, © 2024 sjkuntz (arrays written out to CSV by the project, see the README).
  5100 × 1 s open-loop PRBS run. **Training: the first 70 %**; held out: the last 30 %.
* ``tclab_apmonitor_energy_balance_steps.csv``: from APMonitor/arduino
  (``2_Regression/Energy_balance_MIMO/Python_minimize/data.txt`` @ f36e65a7), Apache-2.0. 599 × 1 s of
  heater steps, another unit state and another day. **Held out here**: nothing is fitted on it.

Both networks are trained with the default options (multiple shooting in windows of at least the slowest time
constant, then single shooting from a fitted initial state). Every row is a free run judged by the tool's default
rule: the training part continues from the state fitted in training; a held-out file starts from a state estimated
on its first tenth (the burn-in, not scored), and with ``tclab_ambient.thn`` the file's own ambient is estimated
there too — nothing is read from the file by hand. The last row, for comparison, sets ``Ta`` by hand to the mean
of the APMonitor file's first ``--rest-samples`` readings (heaters off: they *are* ambient).

    python examples/tclab_fit.py                   # JAX, about a minute
    python examples/tclab_fit.py --backend torch
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tnn_dsl  # noqa: E402
from tnn_dsl.data import read_data  # noqa: E402
from tnn_dsl.data.experiment import split_by_time  # noqa: E402
from tnn_dsl.ir.emit import format_quantity  # noqa: E402

DATA = Path(os.environ.get("TNN_SHARED", ROOT.parent / "shared")) / "data"
PRBS = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
STEPS = DATA / "tclab_apmonitor_energy_balance_steps.csv"


def ambient_from_rest(exp, n: int) -> float:
    """Mean sensor reading (K) over the first ``n`` samples, which must all have every input at 0."""
    U = np.asarray(exp.inputs[:n], dtype=float)
    if n < 1 or np.any(U != 0.0):
        raise SystemExit(f"{exp.path}: the first {n} samples are not at rest (heaters on); cannot read ambient")
    return float(np.nanmean(np.asarray(exp.outputs[:n], dtype=float)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", default="jax", choices=("jax", "torch"))
    ap.add_argument("--split", type=float, default=0.7, help="training fraction of the PRBS run (default 0.7)")
    ap.add_argument("--epochs", type=int, default=150)
    ap.add_argument("--rest-samples", type=int, default=10,
                    help="first samples of the APMonitor file (heaters off) that give its ambient (default 10)")
    ap.add_argument("-o", "--output", default=None, help="also write the model directory here")
    args = ap.parse_args(argv)

    net = tnn_dsl.load(ROOT / "networks" / "tclab" / "tclab.thn")
    net_pe = tnn_dsl.load(ROOT / "networks" / "tclab" / "tclab_ambient.thn")
    (prbs,) = read_data(net, PRBS)
    head, tail = split_by_time(prbs, args.split)
    (steps,) = read_data(net, STEPS)

    nominal = tnn_dsl.TrainedModel(net, {p.name: np.asarray(p.value) for p in net.params if p.is_constant},
                                   {"backend": args.backend})
    t0 = time.perf_counter()
    tm = tnn_dsl.train(net, [head], backend=args.backend, epochs=args.epochs, seed=0, out=args.output)
    tm_pe = tnn_dsl.train(net_pe, [head], backend=args.backend, epochs=args.epochs, seed=0)
    took = time.perf_counter() - t0

    # for comparison: the APMonitor run with Ta set by hand from its own first (heaters-off) samples
    ta_rest = ambient_from_rest(steps, args.rest_samples)
    re_params = dict(tm.params)
    re_params["Ta"] = np.asarray(ta_rest)
    tm_re = tnn_dsl.TrainedModel(net, re_params, tm.meta)

    rows = []
    for label, model, data in [
        ("PRBS first 70 % (training)", tm, head),
        ("PRBS last 30 % (held out)", tm, tail),
        ("APMonitor steps (held out)", tm, steps),
        ("APMonitor steps, tclab_ambient.thn: Ta estimated on the burn-in", tm_pe, steps),
        (f"APMonitor steps, Ta set by hand from its first {args.rest_samples} s", tm_re, steps),
    ]:
        pred = model.predict(data, backend=args.backend)[0]
        ev = model.evaluate(data, backend=args.backend)
        nom = nominal.evaluate(data, backend=args.backend)
        rows.append((label, ev, nom, pred))

    print(f"TCLab two-node network fitted on {PRBS.name} (first {args.split:.0%}), backend {args.backend}, "
          f"{took:.0f} s for both networks, stopped: {tm.meta['stopped']}, {tm_pe.meta['stopped']}")
    print()
    print("| data | start | MAE T1 (K) | MAE T2 (K) | MAE (K) | max (K) | nominal MAE (K) |")
    print("|---|---|---|---|---|---|---|")
    for label, ev, nom, pred in rows:
        s = ev["sensors"]
        start = pred["init"] + (f", {pred['burn_in']}-sample burn-in" if pred["burn_in"] else "")
        print(f"| {label} | {start} | {s['T1']['mae']:.3f} | {s['T2']['mae']:.3f} | {ev['mae']:.3f} | "
              f"{ev['max_error']:.3f} | {nom['mae']:.3f} |")
    print()
    print("fitted parameters (nominal → fitted):")
    for name, rec in tm.meta["fitted"].items():
        p = net.param(name)
        v0, v = float(np.asarray(rec["initial"])), float(np.asarray(rec["value"]))
        if p.dim == {"K": 1.0}:
            print(f"  {name:4s} {v0 - 273.15:8.3f} degC → {v - 273.15:8.3f} degC")
        elif p.unit and p.unit.endswith("/%"):  # SI is per unit fraction (per 100 %): show it per %
            print(f"  {name:4s} {v0 / 100:.4g} {p.unit} → {v / 100:.4g} {p.unit}")
        else:
            print(f"  {name:4s} {format_quantity(v0, p.dim)} → {format_quantity(v, p.dim)}")
    ta_est = rows[3][3]["experiment_params"]["Ta"]
    print(f"  Ta of the APMonitor run: estimated on its burn-in {ta_est - 273.15:.2f} degC (tclab_ambient.thn), "
          f"from its first {args.rest_samples} samples by hand {ta_rest - 273.15:.2f} degC")
    return 0


if __name__ == "__main__":
    sys.exit(main())
