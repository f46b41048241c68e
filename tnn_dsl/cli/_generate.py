"""``tnnc generate case-study -o DIR``: write the case-study data sets (``shared/spec/case-study.md``);
``tnnc generate plate|building --size N -o FILE.thn``: write a large network.

``train.csv`` (4 h, seed 1), ``val.csv`` (2 h, seed 2) and ``ood_<P>_<k>.csv`` (2 h each, inputs widened by
P percent, ``--n-ood`` sets per level, seeds ``--seed-ood`` + k), from the true network
``networks/peltier_heatpipe/truth.thn`` integrated with RK4 at 0.1 s. Deterministic from the seeds; a
directory already holding the same settings (``manifest.json``) is left as it is unless ``--force``. A
directory holding anything else is refused unless ``--force`` (its other files are kept).

``plate``: a square aluminium plate mesh of about N cells (20 mm, 10 mm thick; heaters Q1, Q2 in W, ambient Ta,
sensors T1–T3). ``building``: N rooms, each an interior and an envelope node, neighbours and floors joined
(``tnn_dsl.studies.large_networks``). The files are ordinary ``.thn`` networks for trying the sparse compiler
(``benchmarks/bench_scaling.py``).
"""

from __future__ import annotations

import sys

from ._common import add_backend, add_command


def register(subparsers) -> None:
    p = add_command(subparsers, "generate", "generate synthetic data sets (the thesis case study) or large networks",
                    __doc__)
    p.add_argument("what", choices=("case-study", "plate", "building"), help="what to generate")
    p.add_argument("-o", "--output", required=True, metavar="PATH",
                   help="output directory (case-study) or .thn file (plate, building)")
    p.add_argument("--size", type=int, default=None, metavar="N",
                   help="plate: about N cells (default 10000); building: N rooms (default 100)")
    p.add_argument("--noise", type=float, default=0.0, metavar="SIGMA",
                   help="Gaussian noise on T_out, standard deviation in K (default 0)")
    p.add_argument("--widen", type=float, nargs="*", default=[10, 20, 30, 40], metavar="P",
                   help="out-of-distribution widenings in percent (default 10 20 30 40; none: --widen)")
    p.add_argument("--n-ood", type=int, default=10, metavar="N", help="data sets per widening (default 10)")
    p.add_argument("--seed", "--seed-train", dest="seed_train", type=int, default=1, metavar="S",
                   help="seed of the training set (default 1)")
    p.add_argument("--seed-val", type=int, default=2, metavar="S", help="seed of the validation set (default 2)")
    p.add_argument("--seed-ood", type=int, default=100, metavar="S",
                   help="seed of the first out-of-distribution set per level (default 100)")
    add_backend(p, what="backend that integrates the truth")
    p.add_argument("--force", action="store_true",
                   help="regenerate even if the directory is up to date; write into an existing directory that "
                        "holds other files (they are kept)")
    p.set_defaults(func=run)


def _network(args) -> int:
    from ..core import THN, Diagnostic, TnnError, write_text_atomic
    from ..studies.large_networks import building_thn, plate_size, plate_thn
    from ._common import check_outputs

    size = args.size if args.size is not None else (10000 if args.what == "plate" else 100)
    if not 1 <= size <= 1_000_000:
        raise TnnError(Diagnostic(f"--size must be in 1 … 1000000, got {size}", hint="e.g. --size 10000"))
    check_outputs(args, [(args.output, THN, "-o")], inputs=[])
    if args.what == "plate":
        nx, ny = plate_size(size)
        text = plate_thn(nx, ny)
        what = f"a {nx} x {ny} plate ({nx * ny} nodes)"
    else:
        text = building_thn(size)
        what = f"a {size}-room building ({2 * size} nodes)"
    if args.output == "-":
        sys.stdout.write(text)
    else:
        write_text_atomic(args.output, text)
        print(f"{what} written to {args.output}")
    return 0


def run(args) -> int:
    from ..core import Diagnostic, TnnError
    from ..studies import generate_case_study

    if args.what != "case-study":
        return _network(args)

    bad = [w for w in args.widen if not (0 <= w <= 1000)]
    if bad:
        raise TnnError(Diagnostic(f"--widen {bad[0]:g}: widenings are percentages in [0, 1000]",
                                  hint="e.g. --widen 10 20 30 40"))
    if args.n_ood < 0:
        raise TnnError(Diagnostic(f"--n-ood must be ≥ 0, got {args.n_ood}"))
    res = generate_case_study(
        args.output, noise=args.noise, widen=[w / 100.0 for w in args.widen], n_ood=args.n_ood,
        seed_train=args.seed_train, seed_val=args.seed_val, seed_ood=args.seed_ood, backend=args.backend,
        force=args.force, progress=lambda msg: print(msg, file=sys.stderr),
    )
    n_ood = sum(len(v) for v in res["ood"].values())
    state = "up to date" if res["cached"] else "written"
    print(f"case study {state} in {res['dir']}: train.csv, val.csv, {n_ood} out-of-distribution sets, manifest.json")
    return 0
