"""``tnnc train NET DATA... [--val VAL...] -o MODEL``: fit a network's free parameters and learned
functions to measured data (thesis eq. 4.8) and write a model directory.

Several DATA files are trained together (batched). Validation (``--val``, or ``--val-fraction`` to hold
out the end of each file) is always a free run over each whole validation file; the model with the best
validation MAE is kept (early stopping). Adam runs first, then an L-BFGS polish. Progress (epoch, loss,
validation MAE, time left) goes to stderr. Ctrl-C stops training and saves the best model so far.

Every option can also be given in a YAML file (``--config train.yaml``, keys as the long option names
with ``_`` or ``-``); flags given on the command line win over the file.
"""

from __future__ import annotations

import json
import math
import sys
import time

from ._common import (
    add_backend,
    add_command,
    add_force_flag,
    add_network_and_data,
    add_time_columns,
    check_outputs,
    write_json,
)

# (flag, config field, type, help). `None` type: a store_true/false flag handled below.
_OPTIONS = [
    ("--objective", "objective", str,
     "output-error (fit the free run; default) | ml (then maximise the Kalman-filter likelihood from that fit: "
     "process and measurement noise estimated, standard errors from its Hessian)"),
    ("--epochs", "epochs", int, "Adam epochs (default 300)"),
    ("--lr", "lr", float, "Adam step size in transformed coordinates (default 0.02)"),
    ("--lr-final", "lr_final", float, "cosine decay to lr*LR_FINAL at the end (default 0.1)"),
    ("--rollout", "rollout", str, "auto | free | steady | measured | estimated (default auto)"),
    ("--window", "window", float, "window length in s for windowed rollouts (default: 600 s, at least 50 samples)"),
    ("--batch-size", "batch_size", int, "windows per optimiser step, 0 = all (default 0)"),
    ("--integrator", "integrator", str, "euler | rk4 | expeuler (default rk4)"),
    ("--substeps", "substeps", int, "integrator sub-steps per data step (default: the model's choice)"),
    ("--dtype", "dtype", str, "float64 | float32 (default float64)"),
    ("--clip", "clip", float, "gradient-norm clip (default: 10x the running mean norm)"),
    ("--lam", "lam", float, "lambda of eq. 4.8: weight of the max error per window (default 0)"),
    ("--weight-decay", "weight_decay", float, "L2 weight on learned-function weights (default 0)"),
    ("--continuity", "continuity", float, "multiple-shooting continuity weight (default 10)"),
    ("--lbfgs-iters", "lbfgs_iters", int, "L-BFGS polish iterations, 0 to skip (default 1000)"),
    ("--patience", "patience", int,
     "early stopping after N epochs without a better validation MAE, from half of --epochs on (default 80)"),
    ("--val-every", "val_every", int, "validate every N epochs, 0 = automatic (default 0)"),
    ("--val-fraction", "val_fraction", float, "without --val: hold out this last fraction of each file"),
    ("--init", "init", str, "initial state of every free run: estimate | filter | steady | measured (default "
                            "estimate: fitted with the parameters; on validation files to a burn-in, not scored)"),
    ("--burn-in", "burn_in", float, "burn-in (s) of validation files for --init estimate/filter (default: a "
                                    "tenth of the file)"),
    ("--init-from", "init_from", str, "initialise from another model directory (same names and shapes)"),
    ("--max-restarts", "max_restarts", int, "divergence guard: restarts with a smaller step (default 6)"),
    ("--time-limit", "time_limit", float, "stop Adam after this many seconds of training (best state kept; the "
                                          "first call of each compiled program is not counted)"),
]


def register(subparsers) -> None:
    p = add_command(
        subparsers, "train",
        "fit a network's free parameters and learned functions to data; write a model directory", __doc__)
    add_network_and_data(p)
    p.add_argument("-o", "--output", required=True, metavar="MODEL", help="model directory to write")
    add_backend(p, default=None, shown="jax")
    p.add_argument("--torch-compile", dest="opt_torch_compile", action="store_true", default=None,
                   help="torch backend: compile the rollouts with torch.compile (default: when samples x epochs "
                        ">= 2e6; TNN_TORCH_COMPILE=0/1 forces it)")
    p.add_argument("--seed", type=int, default=None, help="seed (initial weights, minibatches; default 0)")
    p.add_argument("--config", default=None, metavar="train.yaml", help="training options in YAML")
    p.add_argument("--json", default=None, metavar="metrics.json", help="write metrics as JSON ('-' for stdout)")
    for flag, dest, typ, help_ in _OPTIONS:
        p.add_argument(flag, dest=f"opt_{dest}", type=typ, default=None, help=help_)
    p.add_argument("--gamma", nargs="+", default=None, metavar="G|NAME=G",
                   help="gamma of eq. 4.8: one weight for every free parameter, or NAME=G pairs")
    p.add_argument("--freeze", nargs="+", default=None, metavar="NAME",
                   help="parameters or learned functions kept fixed")
    p.add_argument("--no-prefit", dest="opt_prefit", action="store_false", default=None,
                   help="do not pre-fit replace-mode flow functions to the nominal physics")
    p.add_argument("--no-centre-sigmoid", dest="opt_centre_sigmoid", action="store_false", default=None,
                   help="optimise sigmoid MLPs in their own weights instead of tanh coordinates")
    add_time_columns(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no progress display")
    add_force_flag(p)
    p.set_defaults(func=run)


def _gamma(values):
    from ..core import Diagnostic, TnnError

    if values is None:
        return None
    if len(values) == 1 and "=" not in values[0]:
        try:
            return float(values[0])
        except ValueError:
            raise TnnError(Diagnostic(f"--gamma: {values[0]!r} is not a number",
                                      hint="--gamma 0.1 or --gamma C_h1=0.1"))
    out = {}
    for v in values:
        name, _, num = v.partition("=")
        try:
            out[name] = float(num)
        except ValueError:
            raise TnnError(Diagnostic(f"--gamma: {v!r} is not NAME=NUMBER", hint="--gamma C_h1=0.1 U12=1"))
    return out


class _Progress:
    """One live line on a terminal; a line every few seconds otherwise."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.tty = sys.stderr.isatty()
        self.last = 0.0
        self.width = 0

    def __call__(self, info: dict) -> None:
        if self.quiet:
            return
        now = time.perf_counter()
        final = info.get("phase") == "lbfgs" or info.get("epoch") == info.get("epochs")
        if not self.tty and now - self.last < 5.0 and not final and info.get("epoch", 0) != 0:
            return
        self.last = now

        def f(x, unit=" K"):
            return "—" if x is None or not math.isfinite(x) else f"{x:.4g}{unit}"

        eta = info.get("eta", math.nan)
        eta_s = "" if not math.isfinite(eta) else f"  ~{_dur(eta)} left"
        phase = "L-BFGS" if info.get("phase") == "lbfgs" else "epoch"
        line = (f"{phase} {info.get('epoch', 0)}/{info.get('epochs', 0)}  loss {f(info.get('loss'), '')}  "
                f"val MAE {f(info.get('val_mae'))}  best {f(info.get('best_val_mae'))}  "
                f"{_dur(info.get('elapsed', 0.0))}{eta_s}")
        if self.tty:
            pad = max(0, self.width - len(line))
            sys.stderr.write("\r" + line + " " * pad)
            sys.stderr.flush()
            self.width = len(line)
        else:
            print(line, file=sys.stderr)

    def end(self) -> None:
        if self.tty and self.width and not self.quiet:
            sys.stderr.write("\n")
            self.width = 0

    def log(self, msg: str) -> None:
        if self.quiet and not msg.startswith("warning"):
            return
        self.end()
        print(msg, file=sys.stderr)


def _dur(s: float) -> str:
    s = float(s)
    if s < 60:
        return f"{s:.0f} s"
    if s < 3600:
        return f"{s / 60:.1f} min"
    return f"{s / 3600:.1f} h"


def run(args) -> int:
    import tnn_dsl

    from ..core import JSON, Diagnostic, TnnError
    from ..data import read_data, warning_lines
    from ..estimation import estimation_summary
    from ..fit import MODEL_DIR, load_config, train

    overrides = {dest: getattr(args, f"opt_{dest}") for _, dest, _, _ in _OPTIONS}
    overrides["prefit"] = args.opt_prefit
    overrides["centre_sigmoid"] = args.opt_centre_sigmoid
    overrides["gamma"] = _gamma(args.gamma)
    overrides["freeze"] = args.freeze
    overrides["backend"] = args.backend
    overrides["torch_compile"] = args.opt_torch_compile
    overrides["seed"] = args.seed
    cfg = load_config(args.config, **overrides)
    net = tnn_dsl.load(args.net)
    # before any work: the model directory and the JSON file may not destroy anything
    check_outputs(args, [(args.output, MODEL_DIR, "-o"), (args.json, JSON, "--json")],
                  inputs=[args.net, *net.source_files, *args.data, *(args.val or []), args.config, cfg.init_from])
    kw = {"time_col": args.time_col, "dt": args.dt, "time_unit": args.time_unit}
    exps = read_data(net, args.data, **kw)
    vals = read_data(net, args.val, **kw) if args.val else None
    prog = _Progress(args.quiet)
    for e in exps + (vals or []):
        for note in getattr(e, "notes", ()):
            prog.log(f"note: {e.name}: {note}")
    for w in warning_lines(exps + (vals or [])):  # shown also with -q
        print(w, file=sys.stderr)
    interrupted = False
    try:
        tm = train(net, exps, vals, config=cfg, callback=prog, log=prog.log)
    except KeyboardInterrupt:
        prog.end()
        raise
    prog.end()
    tm.save(args.output, force=args.force)
    meta = tm.meta
    stopped = meta.get("stopped")
    interrupted = stopped == "interrupted"
    m = meta.get("metrics", {})
    tr = m.get("train", {})
    va = m.get("validation")
    if not args.quiet or stopped == "diverged":
        win = meta.get("window_s")
        single = "single shooting: one free run per file from a fitted initial state"
        if meta.get("single_shooting") and not win:
            how = single
        elif meta.get("rollout") == "estimated":
            how = f"multiple shooting in windows of {_dur(win)}" + (f", then {single}" if meta.get("single_shooting")
                                                                      else "")
        else:
            how = f"rollout {meta.get('rollout')}" + (f" in windows of {_dur(win)}" if win else "")
        print(f"model written to {args.output}  ({meta.get('backend')}, {how}, "
              f"{_dur(meta.get('train_seconds', 0.0))}{_compiling(meta)}, stopped: {stopped})", file=sys.stderr)
        print(f"  train      MAE {tr.get('mae', math.nan):.4g} K  max {tr.get('max_error', math.nan):.4g} K",
              file=sys.stderr)
        if va:
            print(f"  validation MAE {va.get('mae', math.nan):.4g} K  max {va.get('max_error', math.nan):.4g} K",
                  file=sys.stderr)
        if meta.get("estimation"):
            print("\n" + estimation_summary(meta["estimation"]), file=sys.stderr)
    est = meta.get("estimation") or {}
    if args.json:
        doc = {"model": args.output, "backend": meta.get("backend"), "objective": meta.get("objective"),
               "loglik": est.get("loglik"), "aic": est.get("aic"), "bic": est.get("bic"),
               "n_params": est.get("n_params"), "n_obs": est.get("n_obs"), "estimates": est.get("rows"),
               "stopped": stopped,
               "metrics": meta.get("metrics"), "fitted": meta.get("fitted"), "warnings": meta.get("warnings"),
               "train_seconds": meta.get("train_seconds"), "compile_seconds": meta.get("compile_seconds"),
               "epochs": len(meta.get("curve", [])) - 1}
        from ..core import to_jsonable

        write_json(args.json, json.dumps(to_jsonable(doc), indent=2))
    if stopped == "diverged":
        raise TnnError(Diagnostic(
            f"training diverged; the best model so far was saved to {args.output}. "
            + (meta.get("warnings") or [""])[-1],
            hint="lower --lr (e.g. --lr 0.005), try --integrator expeuler, or check the nominal values"))
    if interrupted:
        print(f"interrupted: the best model so far was saved to {args.output}", file=sys.stderr)
        return 130
    return 0


def _compiling(meta: dict) -> str:
    """``", of which 12 s compiling"`` where the first calls of the compiled programs took a second or more."""
    c = meta.get("compile_seconds")
    return f", of which {_dur(c)} compiling" if isinstance(c, (int, float)) and c >= 1.0 else ""
