"""``tnnc compare A.thn B.thn DATA... [--val VAL...] [--objective ml|output-error]``: fit two networks to the same
data and compare them.

Both are fitted as ``tnnc train`` would (by default with ``--objective ml``: the Kalman-filter likelihood with its
process and measurement noise). Where B is A plus elements (checked from the two networks: a new node, a link split
in series through a new node, a source moved to a new node joined to its old one ...), the likelihood-ratio test
LR = 2(log L_B - log L_A) on k_B - k_A degrees of freedom says whether the extension pays (Bacher & Madsen 2011's
forward selection); otherwise only AIC and BIC compare them. Also printed: each model's free-run MAE and the
one-step-ahead RMS of its Kalman filter, on the --val files where given, else on the training data (labelled so).
With --objective output-error the likelihood is that of the free run's residuals and the test only indicative.
"""

from __future__ import annotations

import json
import sys

from ._common import add_backend, add_command, add_time_columns, check_outputs, write_json


def register(subparsers) -> None:
    p = add_command(subparsers, "compare",
                    "fit two networks to the same data: likelihood-ratio test, AIC/BIC, prediction errors", __doc__)
    p.add_argument("net_a", metavar="A", help="the smaller network (.thn)")
    p.add_argument("net_b", metavar="B", help="the network to test against it, e.g. A plus a node (.thn)")
    p.add_argument("data", nargs="+", metavar="DATA", help="training data files (CSV or Parquet)")
    p.add_argument("--val", nargs="+", default=None, metavar="VAL",
                   help="held-out data files: the free-run MAE and one-step RMS are scored on them")
    p.add_argument("--objective", choices=("ml", "output-error"), default="ml",
                   help="ml (default: the Kalman-filter likelihood) or output-error (the free run's; the test is "
                        "then only indicative)")
    add_backend(p, default=None, shown="jax")
    p.add_argument("--epochs", type=int, default=None, metavar="N",
                   help="Adam epochs of each fit before its L-BFGS polish (default: tnnc train's, 300)")
    p.add_argument("--seed", type=int, default=None, help="seed of each fit (default 0)")
    add_time_columns(p)
    p.add_argument("--json", default=None, metavar="FILE",
                   help="write the comparison as JSON ('-' for stdout; the table then goes to stderr)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    p.set_defaults(func=run)


def run(args) -> int:
    import tnn_dsl

    from ..analysis import compare_models
    from ..core import JSON, to_jsonable

    net_a, net_b = tnn_dsl.load(args.net_a), tnn_dsl.load(args.net_b)
    check_outputs(args, [(args.json, JSON, "--json")],
                  inputs=[args.net_a, args.net_b, *net_a.source_files, *net_b.source_files, *args.data,
                          *(args.val or [])])

    def log(msg: str) -> None:
        if not args.quiet or msg.startswith("warning"):
            print(msg, file=sys.stderr)

    options = {k: v for k, v in (("backend", args.backend), ("epochs", args.epochs), ("seed", args.seed))
               if v is not None}
    cmp = compare_models(net_a, net_b, args.data, val=args.val, objective=args.objective, time_col=args.time_col,
                         dt=args.dt, time_unit=args.time_unit, log=log, **options)
    to_stdout = args.json != "-"
    print(cmp.summary(), file=sys.stdout if to_stdout else sys.stderr)
    if args.json:
        write_json(args.json, json.dumps(to_jsonable(cmp.to_dict()), indent=2))
    return 0
