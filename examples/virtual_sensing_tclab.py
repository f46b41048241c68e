"""Virtual sensing on the real TCLab (thesis §6.4.2): read T1 only, estimate T2 with an extended Kalman filter.

    .venv/bin/python examples/virtual_sensing_tclab.py [--backend jax|torch] [--plot docs/img/ekf_tclab.png]

1. fits networks/tclab/tclab.thn on the Kuntz–Rawlings PRBS run (../shared/data, a training file);
2. tunes one process-noise level q by the innovation likelihood on that same training file (T1 only);
3. runs the filter with T1 only on the PRBS run, on the PRBS run with T1 missing for 1000 s in the middle,
   and on the closed-loop set-point run (a validation-only file: nothing is fitted or tuned on it);
4. compares the T2 estimate with the measured T2 and with the open-loop model's T2 prediction (MAE).
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
from tnn_dsl.estimation.kalman import ekf, open_loop, tune_process_noise  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
TRAIN = DATA / "tclab_kuntz_rawlings_prbs_openloop.csv"
VALID = DATA / "tclab_kuntz_rawlings_closedloop_setpoint.csv"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--data", default=str(DATA), help="folder with the TCLab CSV files")
    ap.add_argument("--plot", default=str(ROOT / "docs" / "img" / "ekf_tclab.png"))
    ap.add_argument("--model-out", default=None, help="keep the fitted model directory here")
    args = ap.parse_args(argv)
    train_csv, valid_csv = Path(args.data) / TRAIN.name, Path(args.data) / VALID.name
    t0 = time.perf_counter()
    tm = tnn_dsl.train(str(ROOT / "networks/tclab/tclab.thn"), str(train_csv), backend=args.backend,
                       epochs=200, out=args.model_out)
    print(f"fitted tclab.thn on {train_csv.name} in {time.perf_counter() - t0:.0f} s: "
          f"T1 MAE {tm.meta['metrics']['train']['sensors']['T1']['mae']:.3f} K, "
          f"T2 MAE {tm.meta['metrics']['train']['sensors']['T2']['mae']:.3f} K (free run)")
    model, params = tm.compiled(args.backend), tm.backend_params(args.backend)
    net = tm.network
    (tr,) = tnn_dsl.read_data(net, str(train_csv))
    q, scores = tune_process_noise(model, params, tr.inputs, tr.outputs, tr.dt, ["T1"])
    print(f"process noise tuned on the training file (T1 only): q = {q:g} K/√s")
    (va,) = tnn_dsl.read_data(net, str(valid_csv))
    rows, runs = [], []
    for label, exp, drop in [("PRBS (training file)", tr, None), ("PRBS, T1 dropout 2000–3000 s", tr, (2000, 3000)),
                             ("closed-loop set-point (validation only)", va, None)]:
        Y = exp.outputs.copy()
        if drop:
            Y[(exp.t >= drop[0]) & (exp.t < drop[1]), 0] = np.nan
        res = ekf(model, params, exp.inputs, Y, exp.dt, ["T1"], process_noise=q)
        _, y_open = open_loop(model, params, exp.inputs, exp.dt, res.states[0])
        e_ekf = float(np.nanmean(np.abs(res.outputs[:, 1] - exp.outputs[:, 1])))
        e_open = float(np.nanmean(np.abs(y_open[:, 1] - exp.outputs[:, 1])))
        rows.append((label, e_ekf, e_open))
        runs.append((label, exp, Y, res, y_open, drop))
    print("\n| run (T1 used, T2 estimated) | T2 MAE, EKF [K] | T2 MAE, open loop [K] | better by |")
    print("|---|---|---|---|")
    for label, a, b in rows:
        print(f"| {label} | {a:.3f} | {b:.3f} | {(1 - a / b) * 100:.0f} % |")
    if args.plot:
        plot(args.plot, runs, q)
        print(f"\nwrote {args.plot}")
    return 0 if all(a < b for _, a, b in rows) else 1


def plot(path, runs, q):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(runs), 1, figsize=(10, 3.0 * len(runs)), squeeze=False)
    for ax, (label, exp, Y, res, y_open, drop) in zip(axes[:, 0], runs):
        tm = exp.t / 60
        ax.plot(tm, exp.outputs[:, 1] - 273.15, color="0.3", lw=0.8, label="T2 measured (not used)")
        ax.plot(tm, y_open[:, 1] - 273.15, "C1--", lw=1.0, label="T2 open-loop model")
        ax.plot(tm, res.outputs[:, 1] - 273.15, "C0", lw=1.1, label="T2 EKF estimate from T1")
        if drop:
            ax.axvspan(drop[0] / 60, drop[1] / 60, color="red", alpha=0.08, label="T1 missing")
        e1 = np.nanmean(np.abs(res.outputs[:, 1] - exp.outputs[:, 1]))
        e0 = np.nanmean(np.abs(y_open[:, 1] - exp.outputs[:, 1]))
        ax.set_title(f"{label}: T2 MAE EKF {e1:.3f} K vs open loop {e0:.3f} K (q = {q:g} K/√s)", fontsize=9,
                     loc="left")
        ax.set_ylabel("T2 [°C]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=4)
    axes[-1, 0].set_xlabel("time [min]")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
