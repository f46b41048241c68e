"""``tnnc fleet train|diagnose NET FLEET -o OUT``: fit (and diagnose) every unit of a fleet with one network
template, as Ray tasks; ``tnnc fleet generate -o DIR``: a synthetic fleet of TCLab-like boards.

FLEET is a directory with one sub-directory per unit (its files named val* are held out, the others trained on;
without a held-out file the last 30 % of each file is held out), a directory of data files (one unit each), or a
YAML manifest:

    units:
      - name: board-017
        train: [board-017/prbs.csv]
        val: [board-017/setpoint.csv]
        columns: {T1: "T1 (degC)"}            # an input or sensor -> this unit's column
        params: {Ta: 22.5 degC}               # known values, fixed for this unit

Each unit's result is written as it arrives under OUT/units/<unit>/ (result.json, model/, extended.thn); a
re-run skips finished units, so Ctrl-C loses nothing finished. A unit with bad data gets a row saying why. The
fleet report (terminal table, OUT/report.json, OUT/report.html, --json) lists per unit its held-out error, the
doctor's accepted findings and its parameters with standard errors; across the fleet each parameter's
distribution, the units outside it (robust z-score, with a reading) and the units grouped by finding.

A local Ray with --workers CPUs is started and stopped (default 2; 0: run in this process without Ray);
--address auto|HOST:PORT uses a running Ray cluster (tnn_dsl installed on its nodes; only this process reads
the data and writes OUT). `fleet train` fits units of one structure (the same known values, one training file
each) together, several per task in one compiled program (--batch N units per task; default auto: the units
spread over the workers, at most 16 per task; --batch 1: one unit per task). Held-out files are only scored,
never used by the fit.
"""

from __future__ import annotations

import json
import sys
import time

from ._common import add_backend, add_command, add_force_flag, add_init, write_json


def register(subparsers) -> None:
    p = add_command(subparsers, "fleet", "fit and diagnose many units (boards, buildings) at once, on Ray", __doc__)
    p.add_argument("action", choices=("train", "diagnose", "generate"),
                   help="train: fit every unit; diagnose: fit and run the model doctor on every unit; generate: "
                        "write a synthetic fleet")
    p.add_argument("net", nargs="?", metavar="NET", help="the network template (.thn)")
    p.add_argument("fleet", nargs="?", metavar="FLEET", help="the fleet: a directory or a YAML manifest")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="output directory")
    p.add_argument("--workers", type=int, default=2, metavar="N",
                   help="CPUs of the local Ray (default 2; 0: one unit after another in this process, no Ray)")
    p.add_argument("--address", default=None, metavar="auto|HOST:PORT", help="use a running Ray cluster")
    p.add_argument("--batch", default="auto", metavar="N|auto",
                   help="units fitted together per task in one compiled program (train; default auto, 1: one by one)")
    p.add_argument("--json", default=None, metavar="OUT", help="write the fleet report as JSON ('-': stdout)")
    p.add_argument("--no-compile-cache", action="store_true",
                   help="do not share JAX's compilation cache between the units (OUT/.jax_cache, or the directory "
                        "JAX_COMPILATION_CACHE_DIR names where set)")
    add_backend(p)
    p.add_argument("--epochs", type=int, default=None, metavar="N", help="training epochs (default: the trainer's)")
    p.add_argument("--budget", type=float, default=None, metavar="S", help="the doctor's wall-clock budget per unit")
    p.add_argument("--top", type=int, default=None,
                   help="the doctor's candidates fitted per round (default 3: the doctor's SHORTLIST_TOP)")
    p.add_argument("--max-rounds", type=int, default=4, help="the doctor's rounds at most (default 4)")
    p.add_argument("--mlp-check", action="store_true",
                   help="let the doctor try MLP extensions per unit (off in a fleet: two MLP trainings per unit)")
    add_init(p)
    g = p.add_argument_group("generate")
    g.add_argument("--units", type=int, default=20, metavar="N", help="boards to generate (default 20)")
    g.add_argument("--faulty", type=int, default=4, metavar="K", help="of which with a planted fault (default 4)")
    g.add_argument("--noise", type=float, default=0.02, metavar="K", help="sensor noise in K (default 0.02)")
    g.add_argument("--seed", type=int, default=0, help="seed (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    add_force_flag(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..core import Diagnostic, TnnError

    t0 = time.monotonic()

    def progress(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.monotonic() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    if args.action == "generate":
        from ..fleet import generate_fleet

        if args.net or args.fleet:
            raise TnnError(Diagnostic("`tnnc fleet generate` takes no NET or FLEET",
                                      hint="tnnc fleet generate -o fleet/ --units 20 --faulty 4"))
        truth = generate_fleet(args.output, n_units=args.units, n_faulty=args.faulty, noise=args.noise,
                               seed=args.seed, force=args.force)
        faults = {u: t["fault"] for u, t in truth["units"].items() if t["fault"]}
        print(f"wrote {len(truth['units'])} boards to {args.output} ({len(faults)} with a planted fault, listed in "
              f"{args.output}/truth.json); template: {_template()}")
        return 0
    if not args.net or not args.fleet:
        raise TnnError(Diagnostic(f"`tnnc fleet {args.action}` needs NET and FLEET",
                                  hint=f"tnnc fleet {args.action} board.thn fleet/ -o fleet_out/"))
    from ..core import JSON
    from ..fleet import FleetOptions, report_text, run_fleet
    from ._common import check_outputs

    check_outputs(args, [(args.json, JSON, "--json")], inputs=[args.net, args.fleet])
    batch = None
    if str(args.batch) != "auto":
        try:
            batch = int(args.batch)
        except ValueError:
            batch = 0
        if batch < 1:
            raise TnnError(Diagnostic(f"--batch must be a positive number of units or auto, got {args.batch!r}",
                                      hint="--batch auto (default), --batch 1 (one unit per task) or e.g. --batch 8"))
    opts = FleetOptions(mode=args.action, backend=args.backend, epochs=args.epochs, top=args.top,
                        max_rounds=args.max_rounds, budget_s=args.budget, mlp_check=args.mlp_check, init=args.init,
                        burn_in=args.burn_in)
    res = run_fleet(args.net, args.fleet, args.output, options=opts, workers=args.workers, address=args.address,
                    force=args.force, progress=progress, compile_cache=not args.no_compile_cache, batch=batch)
    print(report_text(res.report))
    print(f"\n{len(res.ran)} units run, {len(res.skipped)} already finished; {res.seconds:.1f} s; report: "
          f"{args.output}/report.html")
    if args.json:
        from ..core.jsonable import to_jsonable

        write_json(args.json, json.dumps(to_jsonable(res.report), indent=1))
    if res.interrupted:
        return 130
    return 0


def _template() -> str:
    from ..fleet import template_path

    return str(template_path())
