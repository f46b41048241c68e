"""``tnnc evaluate MODEL DATA... [--json FILE] [--plot PNG]``: errors of a trained model on data.

Each data file is simulated as a free run and compared with the measurements after its burn-in: per sensor the
mean absolute error, the max absolute error (thesis eq. 4.9), the bias (mean predicted − measured) and the RMSE, all
in K. The run starts by the initial-state rule ``--init`` (default ``estimate``: fitted to the readings of a burn-in
at the file's start, which is not scored and whose length is printed; a file the model was trained on continues
from its fitted state). ``--plot`` draws measured vs predicted per sensor with the error below.
"""

from __future__ import annotations

import json
import math
import sys

from ._common import (
    add_backend,
    add_command,
    add_force_flag,
    add_init,
    add_time_columns,
    check_outputs,
    write_json,
)


def register(subparsers) -> None:
    p = add_command(
        subparsers, "evaluate",
        "MAE / max error per sensor of a trained model on data files (thesis eq. 4.9)", __doc__)
    p.add_argument("model", metavar="MODEL", help="a model directory written by `tnnc train`")
    p.add_argument("data", nargs="+", metavar="DATA", help="data files (CSV or Parquet)")
    add_backend(p, default=None)
    add_init(p)
    p.add_argument("--json", default=None, metavar="FILE", help="write the metrics as JSON ('-' for stdout)")
    p.add_argument("--plot", default=None, metavar="PNG", help="plot measured vs predicted, with the error below")
    add_time_columns(p)
    add_force_flag(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import plots
    from ..core import IMAGE, JSON, save_figure, to_jsonable
    from ..data import read_data, warning_lines
    from ..fit import error_metrics, load_model

    check_outputs(args, [(args.json, JSON, "--json"), (args.plot, IMAGE, "--plot")], inputs=[args.model, *args.data])
    tm = load_model(args.model)
    exps = read_data(tm.network, args.data, time_col=args.time_col, dt=args.dt, time_unit=args.time_unit)
    for w in warning_lines(exps):
        print(w, file=sys.stderr)
    preds = tm.predict(exps, backend=args.backend, init=args.init, burn_in_s=args.burn_in,
                       log=lambda s: print(s, file=sys.stderr))
    for p in preds:
        for n in p["notes"]:
            print(f"{p['name']}: {n}", file=sys.stderr)
    sensors = [s.name for s in tm.network.sensors]
    metrics = error_metrics(preds, sensors)
    metrics["model"] = args.model
    metrics["backend"] = args.backend or tm.backend
    out = sys.stdout if args.json != "-" else sys.stderr
    print(f"{'data':<28} {'sensor':<12} {'MAE K':>9} {'max K':>9} {'bias K':>9} {'RMSE K':>9} {'n':>7}", file=out)
    for rec in metrics["experiments"]:
        for s in sensors:
            r = rec["sensors"][s]
            print(f"{rec['name'][:28]:<28} {s[:12]:<12} {_f(r['mae'])} {_f(r['max_error'])} {_f(r['bias'])} "
                  f"{_f(r['rmse'])} {r['n']:>7}", file=out)
    if len(metrics["experiments"]) > 1 or len(sensors) > 1:
        print(f"{'all':<28} {'all':<12} {_f(metrics['mae'])} {_f(metrics['max_error'])} {_f(metrics['bias'])} "
              f"{_f(metrics['rmse'])} {metrics['n']:>7}", file=out)
    if args.json:
        write_json(args.json, json.dumps(to_jsonable(metrics), indent=2))
    if args.plot:
        save_figure(plots.predictions(tm.network, preds), args.plot, dpi=110)
        print(f"wrote {args.plot}", file=out)
    return 0


def _f(x) -> str:
    return f"{'—':>9}" if x is None or not math.isfinite(x) else f"{x:>9.4f}"
