"""``tnnc excitation DATA...``: compare how well data files excite the system (thesis §4.2, §5.6.1).

The singular values of the block-Hankel matrix of each file's inputs and its condition number (lower =
richer excitation); files are ranked best first. See ``tnn_dsl.analysis.hankel.excitation`` for the exact
definition (centring, common scaling, constant channels left out).
"""

from __future__ import annotations

import json

from ..core import JSON
from ._common import add_command, add_force_flag, check_outputs, write_json


def register(subparsers) -> None:
    p = add_command(
        subparsers, "excitation", "compare the input excitation of data files (Hankel singular values)",
        description="Rank data files by the condition number of their input block-Hankel matrix (thesis §4.2): "
                    "pseudo-random steps excite more than a single step, which excites more than steady-state "
                    "data. The same window is used for every file.")
    p.add_argument("data", metavar="DATA", nargs="+", help="data files (CSV/Parquet)")
    p.add_argument("--net", metavar="NET", default=None,
                   help="a .thn network: its inputs (read as `tnnc train` reads them) are the channels")
    p.add_argument("--columns", nargs="+", metavar="COL", default=None,
                   help="input columns to use (default: the network's inputs, or every numeric non-time column)")
    p.add_argument("--window", type=int, default=20, help="Hankel window K in samples (default 20)")
    p.add_argument("--stride", type=int, default=1, help="use every n-th sample (default 1)")
    p.add_argument("--json", nargs="?", const="-", metavar="OUT", default=None,
                   help="write the result as JSON (to OUT, or stdout without a name)")
    add_force_flag(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..analysis import excitation

    check_outputs(args, [(None if args.json == "-" else args.json, JSON, "--json")], inputs=[*args.data, args.net])
    net = None
    if args.net:
        from .. import load

        net = load(args.net)
    report = excitation(args.data, net=net, window=args.window, columns=args.columns, stride=args.stride)
    if args.json == "-":
        print(json.dumps(report.to_dict(), indent=2))
        return 0
    print(report.table())
    if args.json:
        write_json(args.json, json.dumps(report.to_dict(), indent=2))
        print(f"wrote {args.json}")
    return 0
