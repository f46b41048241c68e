"""Real-data fits (issue 15): every network that has real training data, trained three ways, judged on the
part of its file it was not trained on.

Networks and data (third-party measurements, see ``../shared/data/README.md``; only train-on files are used):

* ``networks/building/{ti,tite,tith,titeth}.thn`` on ``bacher_madsen_inputPRBS1.csv`` (1691 × 5 min);
* ``networks/tclab/{tclab,tclab_lag}.thn`` on ``tclab_kuntz_rawlings_prbs_openloop.csv`` (5100 × 1 s).

Each is trained on the first 70 % of its file (``split_by_time``) and judged on the last 30 %. Ways:

* ``default``: ``tnn_dsl.train`` with default options (``rollout=auto``: these files are short enough for one
  free run from a fitted initial state, i.e. single shooting);
* ``free+estimate``: ``rollout="free", init="estimate"`` (single shooting with fitted initial states, the
  reference the default should equal);
* ``windows``: ``rollout="estimated"`` (multiple shooting: windows with trainable initial states and a
  continuity penalty, the old default for long files).

Reported per network and way (MAE in K over every sensor's measured samples):

* **train**: the free run over the training part (``tm.evaluate(head)``: it continues from the initial state
  fitted in training, nothing excluded);
* **held out, own file**: the last 30 % as a file of its own (``tm.evaluate(tail)``: initial state estimated
  on a burn-in of a tenth of it, the burn-in not scored). A part from ``split_by_time`` keeps its times
  (t0 > 0), but nothing in a free run reads t0, so it gives the same numbers as a separate CSV file;
* **continued**: one free run over the whole file (``tm.predict(whole)``: the whole file is not a training
  file, so its start is estimated from a burn-in), scored on the rows at and after the split;
* the fit's wall time (compilation included) and, for ``tclab_lag``, the fitted sensor lags.

    python benchmarks/bench_real_data_fits.py            # all six networks, three ways (a few minutes)
    python benchmarks/bench_real_data_fits.py --quick    # ti, tite, tclab with fewer epochs
    python benchmarks/bench_real_data_fits.py --only tite --ways default,windows --no-write

Results go to the ``real-data-fits`` section of ``BENCHMARKS.md`` (``--no-write``: print only).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

DATA = ROOT.parent / "shared" / "data"
BM = "bacher_madsen_inputPRBS1.csv"
TCLAB = "tclab_kuntz_rawlings_prbs_openloop.csv"
SPLIT = 0.7

CASES = {  # network name -> (.thn path relative to the root, data file, read_data options)
    "ti": ("networks/building/ti.thn", BM, {"time_unit": "h"}),
    "tite": ("networks/building/tite.thn", BM, {"time_unit": "h"}),
    "tith": ("networks/building/tith.thn", BM, {"time_unit": "h"}),
    "titeth": ("networks/building/titeth.thn", BM, {"time_unit": "h"}),
    "tclab": ("networks/tclab/tclab.thn", TCLAB, {}),
    "tclab_lag": ("networks/tclab/tclab_lag.thn", TCLAB, {}),
}
QUICK_CASES = ["ti", "tite", "tclab"]
WAYS = {
    "default": {},
    "free+estimate": {"rollout": "free", "init": "estimate"},
    "windows": {"rollout": "estimated"},
}
QUICK_EPOCHS = 60
QUICK_LBFGS = 100


def load_case(name: str):
    """``(network, whole, head, tail)`` for one case (``head``/``tail``: the first 70 % / the rest)."""
    import tnn_dsl
    from tnn_dsl.data import read_data, split_by_time

    rel, fname, opts = CASES[name]
    net = tnn_dsl.load(ROOT / rel)
    (whole,) = read_data(net, DATA / fname, **opts)
    head, tail = split_by_time(whole, SPLIT)
    return net, whole, head, tail


def continued_mae(tm, whole, split: int, backend: str) -> float:
    """MAE (K) of one free run over ``whole`` (start estimated from its burn-in), over the rows ≥ ``split``."""
    (p,) = tm.predict(whole, backend=backend)
    assert p["burn_in"] <= split
    err = np.asarray(p["y"])[split:] - np.asarray(p["measured"])[split:]
    err = err[np.isfinite(err)]
    return float(np.mean(np.abs(err))) if err.size else math.nan


def run_one(name: str, way: str, backend: str, extra: dict) -> dict:
    import tnn_dsl

    net, whole, head, tail = load_case(name)
    t0 = time.perf_counter()
    tm = tnn_dsl.train(net, [head], backend=backend, **WAYS[way], **extra)
    fit_s = time.perf_counter() - t0
    tr = tm.evaluate(head, backend=backend)
    ho = tm.evaluate(tail, backend=backend)
    row = {
        "network": name, "way": way, "options": {**WAYS[way], **extra},
        "rollout": tm.meta.get("rollout"), "window_s": tm.meta.get("window_s"),
        "single_shooting": bool(tm.meta.get("single_shooting", tm.meta.get("rollout") == "free")),
        "train_mae": tr["mae"], "heldout_mae": ho["mae"],
        "heldout_sensors": {s: v["mae"] for s, v in ho["sensors"].items()},
        "heldout_burn_in": (tm.predict(tail, backend=backend)[0]["burn_in"]),
        "continued_mae": continued_mae(tm, whole, head.n_steps, backend),
        "fit_s": fit_s, "stopped": tm.meta.get("stopped"),
        "n_train": head.n_steps, "n_tail": tail.n_steps,
    }
    lags = {s.name: float(np.asarray(tm.params[f"{s.name}.lag"]).reshape(-1)[0])
            for s in net.sensors if s.lag and f"{s.name}.lag" in tm.params}
    if lags:
        row["lags_s"] = lags
    return row


def _warm_up(backend: str) -> None:
    """One tiny fit, so the first timed fit does not pay the backend's one-time start-up."""
    import tnn_dsl

    net, _, head, _ = load_case("ti")
    tnn_dsl.train(net, [head], backend=backend, epochs=2, lbfgs_iters=0)


def _trainer_ran(r: dict) -> str:
    """What the trainer did, from the model's ``meta`` (``rollout``, ``window_s``, ``single_shooting``)."""
    if r["rollout"] == "free":
        return "single shooting"
    if r["window_s"]:
        return f"windows of {r['window_s']:g} s" + (", then single shooting" if r.get("single_shooting") else "")
    return str(r["rollout"])


def table(rows: list[dict], quick: bool, backend: str, extra: dict) -> str:
    """The markdown section: the rows and what they mean."""
    lines = [
        "Each network trained on the first 70 % of its real data file and judged on the last 30 % "
        "(`tnn_dsl.train`, backend " + backend + ", seed 0; "
        + ("default epochs" if not extra else ", ".join(f"{k}={v}" for k, v in extra.items()))
        + "). Ways: **default** = default options; **free+estimate** = `rollout=\"free\", init=\"estimate\"` "
        "(single shooting from fitted initial states, the reference); **windows** = `rollout=\"estimated\"` "
        "(multiple shooting, the old default for long files). MAE in K over all sensors. *train*: "
        "`tm.evaluate(head)` (continues from the fitted initial state); *held out, own file*: "
        "`tm.evaluate(tail)` (initial state estimated on a burn-in of a tenth of the tail, not scored); "
        "*continued*: one free run over the whole file (start estimated from its burn-in), scored on the rows "
        "at and after the split; *fit*: wall time of `train`, compilation included.",
        "",
        "| network | data (train / held-out rows) | way | trainer ran | train MAE (K) | held out, own file (K) "
        "| continued, last 30 % (K) | fit (s) | stopped | sensor lags (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        data = f"{'B&M' if CASES[r['network']][1] == BM else 'TCLab PRBS'} ({r['n_train']} / {r['n_tail']})"
        ho = f"{r['heldout_mae']:.4f}"
        if len(r["heldout_sensors"]) > 1:
            ho += " (" + ", ".join(f"{s} {v:.3f}" for s, v in r["heldout_sensors"].items()) + ")"
        lags = ", ".join(f"{s} {v:.1f}" for s, v in r.get("lags_s", {}).items()) or "–"
        lines.append(f"| {r['network']} | {data} | {r['way']} | {_trainer_ran(r)} | {r['train_mae']:.4f} | {ho} "
                     f"| {r['continued_mae']:.4f} | {r['fit_s']:.1f} | {r['stopped']} | {lags} |")
    by = {(r["network"], r["way"]): r for r in rows}
    notes = []
    for name in dict.fromkeys(r["network"] for r in rows):
        a, b, c = (by.get((name, w)) for w in WAYS)
        if a and b:
            d = a["train_mae"] - b["train_mae"]
            ok = a["train_mae"] <= 1.02 * b["train_mae"] + 0.005
            notes.append(f"{name} {d:+.4f} K" + ("" if ok else " (**worse than 2 % + 5 mK**)"))
        for other in (b, c):
            if a and other and other["heldout_mae"] < a["heldout_mae"] - 0.005 \
                    and other["train_mae"] < a["train_mae"] - 0.005:
                notes.append(f"{name}: **{other['way']} beats the default** in training and held out")
    if notes:
        lines += ["", "Default minus free+estimate, training free-run MAE (the test's tolerance is 2 % + 5 mK): "
                  + "; ".join(notes) + "."]
    if quick or extra:
        lines += ["", "Shortened run (" + ", ".join(f"{k}={v}" for k, v in extra.items())
                  + "): the numbers are not those of the default training."]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help=f"{', '.join(QUICK_CASES)} only, fewer epochs")
    ap.add_argument("--only", default=None, help="comma-separated networks (default: all, --quick: "
                                                 f"{','.join(QUICK_CASES)})")
    ap.add_argument("--ways", default=",".join(WAYS), help=f"comma-separated ways (default {','.join(WAYS)})")
    ap.add_argument("--backend", choices=("jax", "torch"), default="jax")
    ap.add_argument("--epochs", type=int, default=None, help="Adam epochs (default: the trainer's; --quick: "
                                                             f"{QUICK_EPOCHS})")
    ap.add_argument("--lbfgs-iters", type=int, default=None,
                    help=f"L-BFGS iterations (default: the trainer's; --quick: {QUICK_LBFGS})")
    ap.add_argument("--output", default=str(ROOT / "BENCHMARKS.md"), help="markdown file to update")
    ap.add_argument("--json", default=None, help="also write the rows to this JSON file")
    ap.add_argument("--no-write", action="store_true", help="print the table, do not touch the markdown file")
    args = ap.parse_args(argv)

    names = args.only.split(",") if args.only else (QUICK_CASES if args.quick else list(CASES))
    ways = args.ways.split(",")
    bad = [n for n in names if n not in CASES] + [w for w in ways if w not in WAYS]
    if bad:
        ap.error(f"unknown network or way: {', '.join(bad)}")
    missing = sorted({CASES[n][1] for n in names if not (DATA / CASES[n][1]).exists()})
    if missing:
        print(f"data not found in {DATA}: {', '.join(missing)}", file=sys.stderr)
        return 1
    extra: dict = {}
    epochs = args.epochs if args.epochs is not None else (QUICK_EPOCHS if args.quick else None)
    lbfgs = args.lbfgs_iters if args.lbfgs_iters is not None else (QUICK_LBFGS if args.quick else None)
    if epochs is not None:
        extra["epochs"] = epochs
    if lbfgs is not None:
        extra["lbfgs_iters"] = lbfgs

    _warm_up(args.backend)
    rows = []
    for name in names:  # one training at a time: the fit times must not compete for the cores
        for way in ways:
            r = run_one(name, way, args.backend, extra)
            rows.append(r)
            print(f"{name:10s} {way:14s} train {r['train_mae']:.4f}  held out {r['heldout_mae']:.4f}  "
                  f"continued {r['continued_mae']:.4f}  fit {r['fit_s']:.1f} s  {_trainer_ran(r)}"
                  + (f"  lags {r['lags_s']}" if "lags_s" in r else ""), flush=True)
    md = table(rows, args.quick, args.backend, extra)
    print("\n" + md)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "quick": args.quick}, indent=1))
    if not args.no_write:
        from _report import write_section

        write_section("real-data-fits", md, path=args.output,
                      title="Real-data fits: default vs single shooting vs windows (issue 15)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
