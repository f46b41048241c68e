"""``tnnc sensitivity NET [DATA...]``: which parameters matter, and which can be learned from the data.

Prints the ranked steady-state sensitivity table (thesis §4.3, with the exact eq. 3.4 derivative beside the
α-slope), and with DATA the dynamic sensitivity, the Fisher identifiability summary and a recommendation of
the parameters worth making learnable. ``--plot`` writes a bar chart like the thesis's Figure 5.3 and
``--json`` everything as JSON.
"""

from __future__ import annotations

import json
import re

from ..core import IMAGE, JSON, Diagnostic, TnnError
from ._common import INTEGRATORS, add_backend, add_command, add_force_flag, check_outputs, write_json


def register(subparsers) -> None:
    p = add_command(
        subparsers, "sensitivity", "steady-state and dynamic parameter sensitivity, identifiability, what to learn",
        description="Rank every parameter and component heat flow by the steady-state sensitivity of the sensors "
                    "(thesis §4.3: each scaled by α in [1-δ, 1+δ], slope of a line through the steady outputs), "
                    "with the exact derivative (eq. 3.4) beside it. With DATA: the sensitivity along the data "
                    "(eq. 3.2), Fisher-information identifiability (standard errors, correlated pairs explained) "
                    "and a recommendation of the parameters worth making learnable.")
    p.add_argument("net", metavar="NET", help="the .thn network")
    p.add_argument("data", metavar="DATA", nargs="*", help="data file(s) (CSV/Parquet) for the dynamic analysis")
    p.add_argument("--inputs", nargs="+", metavar="NAME=VALUE", default=[],
                   help="constant inputs for the steady state, in the file's units (temperatures in the network's "
                        "`units temperature`); default: the data mean")
    p.add_argument("--delta", type=float, default=0.2, help="α range [1-δ, 1+δ] (default 0.2, as the thesis)")
    p.add_argument("--n-alpha", type=int, default=5, help="number of α values (default 5)")
    p.add_argument("--sigma", type=float, default=0.1, help="sensor noise standard deviation in K (default 0.1)")
    p.add_argument("--max-se", type=float, default=0.1,
                   help="largest relative standard error still called identifiable (default 0.1 = 10 %%)")
    p.add_argument("--params", nargs="+", metavar="NAME", default=None,
                   help="parameters of the identifiability analysis (default: every constant)")
    add_backend(p)
    p.add_argument("--dtype", choices=("float64", "float32"), default="float64")
    p.add_argument("--integrator", choices=INTEGRATORS, default="rk4",
                   help="integrator for the data rollout (default rk4)")
    p.add_argument("--top", type=int, default=None, help="show only the first N rows of the table")
    p.add_argument("--json", metavar="OUT", default=None, help="write the full report as JSON ('-' for stdout)")
    p.add_argument("--plot", metavar="PNG", default=None, help="write the ranked bar chart (thesis Figure 5.3)")
    add_force_flag(p)
    p.set_defaults(func=run)


_ASSIGN = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*=\s*([-+0-9.eE]+)\s*$")


def parse_inputs(net, items: list[str]) -> dict[str, float]:
    """``["I=1.5", "Ta=22"]`` → SI values: temperature inputs from the network's temperature unit to K, the
    others by their declared unit (``%`` → 0.01)."""
    from ..data import to_kelvin, unit_factor

    by = {i.name: i for i in net.inputs}
    out: dict[str, float] = {}
    for item in items:
        m = _ASSIGN.match(item)
        if not m:
            raise TnnError(Diagnostic(f"cannot read --inputs {item!r}",
                                      hint="write NAME=VALUE, e.g. --inputs I=1.5 Ta=22"))
        name, text = m.group(1), m.group(2)
        if name not in by:
            raise TnnError(Diagnostic(f"--inputs: the network has no input {name!r}",
                                      hint=f"its inputs are: {', '.join(by) or '(none)'}"))
        try:
            value = float(text)
        except ValueError:
            raise TnnError(Diagnostic(f"--inputs: {text!r} is not a number", hint="e.g. --inputs I=1.5")) from None
        inp = by[name]
        if inp.is_temperature:
            out[name] = float(to_kelvin(value, net.temperature_unit))
        else:
            try:
                out[name] = value * unit_factor(inp.unit)
            except ValueError as err:
                raise TnnError(Diagnostic(f"--inputs: cannot convert {name}: {err}")) from None
    return out


def run(args) -> int:
    from .. import load
    from ..analysis import sensitivity

    check_outputs(args, [(args.json, JSON, "--json"), (args.plot, IMAGE, "--plot")], inputs=[args.net, *args.data])
    net = load(args.net)
    inputs = parse_inputs(net, args.inputs)
    report = sensitivity(net, args.data or None, inputs=inputs, backend=args.backend, dtype=args.dtype,
                         delta=args.delta, n_alpha=args.n_alpha, sigma=args.sigma, max_se=args.max_se,
                         fisher_params=args.params, integrator=args.integrator)
    if args.json == "-":
        print(json.dumps(report.to_dict(), indent=2))
    else:
        print(report.table(top=args.top))
        if args.json:
            write_json(args.json, json.dumps(report.to_dict(), indent=2))
            print(f"wrote {args.json}")
    if args.plot:
        report.plot(args.plot)
        if args.json != "-":
            print(f"wrote {args.plot}")
    return 0
