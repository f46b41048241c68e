"""``tnnc diagnose NET TRAIN... [--val VAL...] [-o EXTENDED.thn] [--model DIR] [--report DIR] [--json OUT]
[--budget S]``: the model doctor.

Fits the network's free parameters on TRAIN, shows what the free-run simulation gets wrong on held-out data
(--val, else the last 30 % of each training file), ranks candidate causes taken from the network itself (a
parameter depending on an input or a temperature, an unmodelled heat load, a missing link, a missing radiation
path, a sensor offset or lag, a heat capacity behind a link or a source, an unused data column, a wrong
constant) by a score test, fits the best few, keeps one only if it pays on the held-out data (Diebold–Mariano
test on the held-out squared errors with a charge for the extra parameters, p < 0.05, and at least 10 % lower
MAE), and repeats (forward selection). Writes the extended network (-o), the diagnosed model at the doctor's
values (--model: a model directory, the MLP check's trained MLP where it chose one; `tnnc evaluate DIR VAL`
gives the report's held-out numbers), a JSON document (--json) and a self-contained HTML report (--report).
Every free run starts from an estimated initial state (--init, default estimate: fitted with the parameters on a
training file, from a burn-in that is not scored on a held-out file); a file that does not start at rest is
named in a warning.
"""

from __future__ import annotations

import json
import sys
import time

from ._common import (
    add_backend,
    add_command,
    add_force_flag,
    add_init,
    add_network_and_data,
    check_outputs,
    write_json,
)


def register(subparsers) -> None:
    p = add_command(
        subparsers, "diagnose",
        "find what a network gets wrong on measured data, name the cause, extend the model", __doc__)
    add_network_and_data(p, "train", val_help="held-out data files")
    p.add_argument("-o", "--output", default=None, metavar="EXTENDED.thn", help="write the extended network here")
    p.add_argument("--model", default=None, metavar="DIR",
                   help="write the diagnosed model here (a model directory: the extension at the doctor's fitted "
                        "values, the trained MLP where the MLP check chose it; `tnnc evaluate DIR VAL` gives the "
                        "report's held-out numbers)")
    p.add_argument("--report", default=None, metavar="DIR", help="write an HTML report (DIR/index.html)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the findings as JSON")
    p.add_argument("--budget", type=float, default=None, metavar="S", help="wall-clock budget in seconds")
    add_backend(p)
    p.add_argument("--top", type=int, default=None,
                   help="distinct candidates fitted properly per round (default 3: the doctor's SHORTLIST_TOP)")
    p.add_argument("--max-rounds", type=int, default=4, help="rounds of forward selection at most (default 4)")
    p.add_argument("--no-mlp-check", action="store_true",
                   help="do not check the doctor's linear clauses against MLPs started as them (done when a "
                        "structured residual is left)")
    p.add_argument("--mlp-time", type=float, default=60.0, metavar="S",
                   help="training time of that check's MLP (and of the linear law, where the check starts from "
                        "nominal values) (default 60)")
    add_init(p, ("estimate", "steady", "measured"),
             estimate_help="estimate (default: a training file's fitted with the parameters, a held-out file's from "
                           "a burn-in at its start that is not scored)")
    p.add_argument("--objective", choices=("output-error", "ml"), default="output-error",
                   help="what decides between candidates: output-error (default; the free run, held-out test on "
                        "squared errors) or ml (the Kalman-filter likelihood: likelihood-ratio test with the held-out "
                        "one-step log-likelihood as the check, largest likelihood first; slower)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_force_flag(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..core import JSON, THN
    from ..doctor import REPORT_DIR, diagnose
    from ..fit import MODEL_DIR

    check_outputs(args, [(args.output, THN, "-o"), (args.model, MODEL_DIR, "--model"), (args.report, REPORT_DIR,
                                                                                      "--report"),
                         (args.json, JSON, "--json")],
                  inputs=[args.net, *args.train, *(args.val or [])])
    t0 = time.monotonic()
    # the data's warnings (a sensor column empty, temperatures in the wrong unit), shown even with --quiet
    import tnn_dsl

    from ..data import read_data, warning_lines

    net = tnn_dsl.load(args.net)
    for w in warning_lines(read_data(net, [*args.train, *(args.val or [])])):
        print(w, file=sys.stderr)

    if args.backend == "jax":
        # the doctor compiles some programs again after letting them go for memory: this process keeps those that
        # took a while to compile in a cache of its own, read back instead (compiler.backends.jax_ops)
        from ..compiler.backends.jax_ops import keep_programs_for_this_process

        keep_programs_for_this_process()
    from ..core.memory import freeze_live_objects

    freeze_live_objects()  # this process is ours: the imports' objects out of every later full collection

    def progress(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.monotonic() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    d = diagnose(args.net, args.train, val=args.val, budget_s=args.budget, backend=args.backend,
                 progress=progress, top=args.top, max_rounds=args.max_rounds, output=args.output,
                 mlp_check=not args.no_mlp_check, mlp_time=args.mlp_time, force=args.force, init=args.init,
                 burn_in=args.burn_in, objective=args.objective, model_dir=args.model,
                 release_jax_caches=True,  # this process is ours
                 stop_on_ctrl_c=True)  # Ctrl-C: what was found so far is reported and written (doctor.stopping)
    print(d.summary())
    if d.diff:
        print("\nextension (diff):")
        print(d.diff)
    if args.json:
        write_json(args.json, json.dumps(d.to_dict(), indent=2))
        progress(f"JSON written to {args.json}")
    if args.report:
        from ..doctor import write_report

        path = write_report(d, args.report, force=args.force)
        progress(f"report written to {path}")
    if (d.budget or {}).get("interrupted"):
        print(f"interrupted: stopped {d.budget['ran_out']}; what was found so far is above"
              + (" and written" if args.output or args.json or args.report else ""), file=sys.stderr)
        return 130
    return 0
